"""``mbtool serve``'s I/O: the device of ``mbtool.device.model`` on a TCP port or a serial line.

* TCP: one thread, ``selectors`` over the listener and every client connection,
  each connection with its own framer (MBAP, or RTU/ASCII over TCP for masters
  that talk to serial device servers).  A client that sends bytes that are not
  MBAP is disconnected (what pymodbus and most devices do: after a bad header
  the stream cannot be resynchronised); the other clients never notice.
  No client can hold the others up or make memory grow: sockets never block,
  at most ``max_clients`` are served, each is read ``RECV_SIZE`` bytes a turn,
  its framer keeps at most one frame (the framers drop what cannot be one), its
  unsent replies are capped at ``OUT_LIMIT`` (past it its requests are no longer
  read: the kernel's buffers and then the client's own sends take the
  back-pressure), and a client that completes no request and takes no reply for
  ``idle_timeout`` seconds is closed, so one that never sends, drips a byte a
  minute or never reads its replies gives its slot back.
* Nor can idle connections lock it: one that has completed no request
  ``first_request_timeout`` seconds after connecting is closed, and a newcomer
  past ``max_clients`` takes the slot of the least recently used idle client
  (nothing owed to it or unsent), one that never completed a request first
  (the Modbus TCP implementation guide's connection management: a server out of
  connections closes the oldest unused one).  Only when every client is busy is
  the newcomer closed at once.
* Serial: pyserial (device path or URL), frames ended by implicit length or by
  t3.5 of silence (spec §2), replies sent no sooner than t3.5 after the request.
* Faults of the I/O layer: delay, drop and checksum corruption of replies.
* Who answers is pluggable (``answerer``): the simulated device by default, or a gateway's
  forwarder (``mbtool.link.forward``, for ``mbtool bridge``).  An answer that takes a bus's
  time is ``queued``: on TCP a worker thread answers one request at a time, in the order they
  came, while the loop goes on accepting, reading and sending.  Each client has at most one
  request in the queue and its socket is not read until that one is answered, so the clients
  take turns: none can hold the others up, however fast it sends.

Every wait is bounded by ``TICK`` so a stop request (Ctrl-C, SIGTERM) is seen
within a tenth of a second.
"""

from __future__ import annotations

import contextlib
import heapq
import queue
import random
import selectors
import signal
import socket
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from typing import Protocol

from mbtool.codec.errors import RequestError
from mbtool.codec.framing import Frame, Framer, Rejected, device_framer
from mbtool.codec.record import record
from mbtool.codec.timing import silent_interval
from mbtool.device.model import Device
from mbtool.errors import ConnectionFailed, NoResponse
from mbtool.link import IN_PROCESS
from mbtool.link.transport import Target
from mbtool.link.transport import parse_target as parse_link_target

TICK = 0.1  # longest wait before the loop looks at the stop flag again
TCP_GAP = 0.05  # RTU over TCP: a pause this long ends a frame whose length is unknown
# On a serial line t3.5 ends a frame (spec §2), but ptys and USB adapters deliver bytes in
# bursts with pauses of several ms inside one frame; a frame whose length is known never
# waits for it, so only an unknown function code or a broken frame pays this.
MIN_SERIAL_GAP = 0.01
MAX_CLIENTS = 64
IDLE_TIMEOUT = 60.0  # seconds without a whole request or a reply taken before a client is closed
FIRST_REQUEST_TIMEOUT = 5.0  # seconds from connecting to a first whole request
RECV_SIZE = 4096  # bytes read from one client per turn of the loop: the others get their turn
# Replies queued for a client that does not read them; past this its requests wait in the
# kernel.  One turn's read can still add a burst (at most 4096 / 8 requests of 260-byte
# replies, 133 KB), so a client costs at most about 200 KB.
OUT_LIMIT = 64 * 1024
ACCEPTS_PER_TURN = 16  # a burst of connections cannot starve the clients already served
WORKER_STOP = 10.0  # seconds a stop waits for the queued answer under way
_WAKE = object()  # the selector's key for the worker's wake-ups


@record
class IoFaults:
    delay: float = 0.0  # seconds before each reply
    drop: float = 0.0  # fraction of replies never sent
    corrupt: float = 0.0  # fraction of replies sent with a wrong CRC/LRC
    # Devices that drop a request sent too soon (TCP clients): within min_gap of the reply
    # before it, or within settle of the connection being accepted.
    min_gap: float = 0.0
    settle: float = 0.0
    # A gateway that leaks connections: it answers only the first N requests of each.
    connection_requests: int = 0
    # Replies that break the spec harmlessly (Modbus TCP), for mbtool's --lenient:
    pad: int = 0  # zero bytes after the reply's PDU, counted in the MBAP length
    byte_count_off: int = 0  # added to the byte count of FC 01-04 replies; the data stays whole
    reply_unit: int | None = None  # the unit id every reply carries, as a confused gateway sends


def parse_target(text: str) -> Target:
    """tcp://HOST[:PORT] (PORT 0: any free port) or a serial device path / pyserial URL."""
    target = parse_link_target(text, listening=True)
    if target.scheme in IN_PROCESS:
        raise RequestError(f"{target} is the in-process device; serve on tcp://HOST:PORT or a serial port")
    return target


class Stats:
    """What the live view and the log show: requests, clients, the last frames."""

    def __init__(self) -> None:
        self.started = time.monotonic()
        self.requests = 0
        self.replies = 0
        self.dropped = 0
        self.corrupted = 0
        self.clients = 0
        self.connections = 0
        self.refused = 0  # connections closed at once: max_clients connected, none of them idle
        self.evicted = 0  # idle clients closed to give their slot to a newcomer
        self.expired = 0  # clients closed by the idle timeout
        self.unused = 0  # clients closed by the first-request timeout
        self.frames: deque[tuple[float, str, str, bytes, str]] = deque(maxlen=12)
        self.listening = ""

    def frame(self, direction: str, peer: str, adu: bytes, note: str = "") -> None:
        self.frames.append((time.monotonic() - self.started, direction, peer, adu, note))


class Answerer(Protocol):
    def answer(self, event: Frame | Rejected, framer: Framer, peer: str) -> bytes | None:
        """The reply ADU to a request from ``peer``, or None when no reply is due."""


class Responder:
    """Turns framer events into reply bytes: the device's answer with the faults applied."""

    def __init__(
        self,
        device: Device,
        faults: IoFaults,
        stats: Stats,
        rng: random.Random,
        log: Callable[[str, str, bytes, str], None],
    ) -> None:
        self.device = device
        self.faults = faults
        self.stats = stats
        self.rng = rng
        self.log = log

    def answer(self, event: Frame | Rejected, framer: Framer, peer: str) -> bytes | None:
        if isinstance(event, Rejected):
            self.stats.frame("bad", peer, event.data, str(event.error))
            self.log("bad", peer, event.data, str(event.error))
            self.device.rejected(event)
            return None
        self.stats.requests += 1
        self.stats.frame("RX", peer, event.adu)
        self.log("RX", peer, event.adu, "")
        reply = self.device.answer_frame(event, framer)
        if reply is None:
            why = self._why_silent(event.unit)
            self.stats.frame("--", peer, b"", why)
            self.log("--", peer, b"", why)
            return None
        if self.faults.drop and self.rng.random() < self.faults.drop:
            self.stats.dropped += 1
            self.stats.frame("--", peer, b"", "reply dropped (--drop)")
            self.log("drop", peer, reply, "reply dropped (--drop)")
            return None
        if framer.name == "tcp" and (
            self.faults.pad or self.faults.byte_count_off or self.faults.reply_unit is not None
        ):
            reply = deviate(reply, self.faults)
        if self.faults.corrupt and self.rng.random() < self.faults.corrupt:
            reply = corrupt_checksum(reply, framer.name)
            self.stats.corrupted += 1
            note = "checksum corrupted (--corrupt)"
        else:
            note = ""
        self.stats.replies += 1
        self.stats.frame("TX", peer, reply, note)
        self.log("TX", peer, reply, note)
        return reply

    def _why_silent(self, unit: int) -> str:
        if unit == 0:
            return "broadcast: applied, never answered"
        if unit not in self.device.units:
            return f"unit {unit} is not served: ignored"
        station = self.device.stations.get(unit)
        if station is not None and station.listen_only:
            return "listen-only mode: no reply"
        return "no reply due"


def deviate(adu: bytes, faults: IoFaults) -> bytes:
    """A Modbus TCP reply bent the ways --pad, --byte-count-off and --reply-unit ask."""
    header, pdu = bytearray(adu[:7]), bytearray(adu[7:])
    if faults.byte_count_off and pdu and pdu[0] in (0x01, 0x02, 0x03, 0x04):
        pdu[1] = (pdu[1] + faults.byte_count_off) & 0xFF
    pdu += bytes(faults.pad)
    if faults.reply_unit is not None:
        header[6] = faults.reply_unit
    header[4:6] = (len(pdu) + 1).to_bytes(2, "big")  # the MBAP length: unit id and PDU
    return bytes(header + pdu)


def corrupt_checksum(adu: bytes, framer_name: str) -> bytes:
    """The reply with its CRC (RTU) or LRC (ASCII) made wrong; the rest untouched."""
    if framer_name == "rtu":
        return adu[:-1] + bytes([adu[-1] ^ 0xFF])
    if framer_name == "ascii":
        # ':' ... LRC(2 hex) CR LF: replace the LRC by another valid hex pair.
        lrc_text = adu[-4:-2]
        wrong = (int(lrc_text, 16) ^ 0x5A) & 0xFF
        return adu[:-4] + f"{wrong:02X}".encode() + adu[-2:]
    return adu


class Server:
    """Runs until ``stop()`` (called from a signal handler) or a fatal error on the port."""

    def __init__(
        self,
        device: Device | None,
        target: Target,
        framer_name: str,
        *,
        answerer: Answerer | None = None,
        queued: bool = False,
        faults: IoFaults | None = None,
        seed: int | None = None,
        settings=None,
        log: Callable[[str, str, bytes, str], None] | None = None,
        max_clients: int = MAX_CLIENTS,
        idle_timeout: float | None = IDLE_TIMEOUT,
        first_request_timeout: float | None = FIRST_REQUEST_TIMEOUT,
    ) -> None:
        self.device = device
        self.target = target
        self.framer_name = framer_name
        from mbtool.link.transport import SerialSettings

        self.settings = settings or SerialSettings()
        self.baud = self.settings.baud
        self.faults = faults or IoFaults()
        self.stats = Stats()
        self._stop = False
        self._log = log or (lambda direction, peer, data, note: None)
        self.responder: Answerer = answerer or Responder(
            device, self.faults, self.stats, random.Random(seed), self._log
        )
        # queued: answers take a bus's time, given one at a time by a worker thread (TCP).
        self.queued = queued
        self._jobs: queue.SimpleQueue[tuple[_Client, Frame] | None] = queue.SimpleQueue()
        self._answered: deque[tuple[_Client, bytes | None]] = deque()
        self._worker: threading.Thread | None = None
        self._failure: BaseException | None = None  # what stopped the worker, raised by the loop
        self._pending: list[tuple[float, int, Callable[[], None]]] = []  # (due, seq, send)
        self._seq = 0
        self._tick: Callable[[], None] = lambda: None
        self.max_clients = max_clients
        self.idle_timeout = idle_timeout or None  # 0 or None: never
        self.first_request_timeout = first_request_timeout or None
        self._clients: set[_Client] = set()
        self._swept = 0.0

    def stop(self) -> None:
        self._stop = True

    @contextlib.contextmanager
    def stopped_by_signals(self) -> Iterator[None]:
        """Inside, Ctrl-C and SIGTERM stop the server cleanly (the loop ends, clients are closed)
        instead of interrupting it; the handlers before come back afterwards."""
        previous = {
            sig: signal.signal(sig, lambda signum, frame: self.stop())
            for sig in (signal.SIGINT, signal.SIGTERM)
        }
        try:
            yield
        finally:
            for sig, handler in previous.items():
                signal.signal(sig, handler)

    def _later(self, due: float, send: Callable[[], None]) -> None:
        self._seq += 1
        heapq.heappush(self._pending, (due, self._seq, send))

    def _send_due(self) -> None:
        now = time.monotonic()
        while self._pending and self._pending[0][0] <= now:
            _, _, send = heapq.heappop(self._pending)
            send()

    def _wait(self, default: float) -> float:
        if not self._pending:
            return default
        return max(0.0, min(default, self._pending[0][0] - time.monotonic()))

    # -- TCP ------------------------------------------------------------------------------

    def open(self) -> None:
        """Bind the port or open the serial line; ConnectionFailed (exit 6) if it cannot be."""
        if self.target.scheme == "tcp":
            self._open_tcp()
        else:
            self._open_serial()

    def _open_tcp(self) -> None:
        host, port = self.target.host, self.target.port
        try:
            infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
            family, kind, proto, _, address = infos[0]
            listener = socket.socket(family, kind, proto)
        except OSError as error:
            raise ConnectionFailed(f"cannot listen on {host}:{port}: {error.strerror or error}") from None
        try:
            listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            listener.bind(address)
            # Room for a burst of connections: past max_clients they are accepted and closed
            # at once, which beats leaving them to time out on a full backlog.
            listener.listen(128)
        except OSError as error:
            listener.close()
            raise ConnectionFailed(f"cannot listen on {host}:{port}: {error.strerror or error}") from None
        listener.setblocking(False)
        self.listener = listener
        bound = listener.getsockname()
        shown = f"[{bound[0]}]" if ":" in bound[0] else bound[0]
        self.stats.listening = f"tcp://{shown}:{bound[1]}"
        self.selector = selectors.DefaultSelector()
        self.selector.register(listener, selectors.EVENT_READ, None)
        if self.queued:
            # The worker wakes the loop with a byte when it has answered.
            self._wake, self._waker = socket.socketpair()
            self._wake.setblocking(False)
            self._waker.setblocking(False)
            self.selector.register(self._wake, selectors.EVENT_READ, _WAKE)
            self._worker = threading.Thread(target=self._work, name="mbtool-bus", daemon=True)
            self._worker.start()

    def _accept(self) -> None:
        accepted: list[_Client] = []
        for _ in range(ACCEPTS_PER_TURN):
            try:
                conn, address = self.listener.accept()
            except OSError:  # nothing left to accept, or out of descriptors: try next turn
                return
            peer = f"{address[0]}:{address[1]}"
            if len(self._clients) >= self.max_clients and not self._give_slot(accepted):
                # Close at once rather than run out of descriptors or keep the master waiting
                # for a reply that will never come; the clients already served never notice.
                conn.close()
                self.stats.refused += 1
                clients = "1 client" if self.max_clients == 1 else f"{self.max_clients} clients"
                why = f"refused: {clients} already connected and busy (--max-clients)"
                self.stats.frame("refuse", peer, b"", why)
                self._log("refuse", peer, b"", why)
                continue
            conn.setblocking(False)
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            client = _Client(conn, peer, device_framer(self.framer_name))
            self.selector.register(conn, client.events, client)
            self._clients.add(client)
            accepted.append(client)
            self.stats.clients += 1
            self.stats.connections += 1
            self._log("open", peer, b"", "connected")
            # A request already waiting is answered now: the newcomer has used its slot
            # before the next one looks for an idle client.
            self._receive(client)

    def _give_slot(self, accepted: list[_Client]) -> bool:
        """Close the least recently used idle client for a newcomer; False if none may go.

        Idle: nothing owed to it or unsent, so no transaction is cut short.  While any client
        has completed no request, the oldest of those goes, and a client that has used its
        slot stays; but those accepted in this turn are spared (the newcomer is refused
        instead), so a burst cannot push out a newcomer before its request could be read.
        Otherwise the client longest without a request or a reply taken goes.
        """
        idle = [c for c in self._clients if not c.owed and not c.out]
        unused = [c for c in idle if not c.requests]
        # A master sends its request whole as soon as it connects: a client holding the start
        # of a request it never finishes goes first, even one accepted in this turn, so a burst
        # of such connections cannot crowd out a newcomer whose request is still on its way.
        stalled = [c for c in unused if c.framer.buffered]
        if unused:
            older = stalled or [c for c in unused if c not in accepted]
            if not older:
                return False
            victim = min(older, key=lambda c: c.connected)
            why = "gave its slot to a newcomer: no request since it connected"
        elif idle:
            victim = min(idle, key=lambda c: c.last_active)
            why = f"gave its slot to a newcomer: idle for {time.monotonic() - victim.last_active:.1f} s"
        else:
            return False
        self.stats.evicted += 1
        self.stats.frame("close", victim.peer, b"", why)
        self._close(victim, why + " (--max-clients)")
        return True

    def _close(self, client: _Client, why: str) -> None:
        if client.closed:
            return
        client.closed = True
        self.selector.unregister(client.sock)
        client.sock.close()
        self._clients.discard(client)
        client.out.clear()
        self.stats.clients -= 1
        self._log("close", client.peer, b"", why)

    def _receive(self, client: _Client) -> None:
        try:
            data = client.sock.recv(RECV_SIZE)
        except (BlockingIOError, InterruptedError):
            return
        except OSError as error:
            self._close(client, error.strerror or str(error))
            return
        if not data:
            self._close(client, "closed by the client")
            return
        client.framer.feed(data)
        client.last_data = time.monotonic()
        self._events(client, client.framer.next_event)

    def _events(self, client: _Client, first: Callable[[], Frame | Rejected | None]) -> None:
        event = first()
        while event is not None and not client.closed:
            if isinstance(event, Rejected) and self.framer_name == "tcp":
                self.responder.answer(event, client.framer, client.peer)
                self._close(client, f"not Modbus TCP: {event.error}")
                return
            if isinstance(event, Frame):
                # Only a whole request counts as activity: bytes that never make one
                # (a drip, garbage) do not keep a client's slot.
                client.last_active = now = time.monotonic()
                client.requests += 1
                too_soon = self._too_soon(client, now)
                if too_soon:
                    self.stats.dropped += 1
                    self.stats.frame("--", client.peer, event.adu, too_soon)
                    self._log("drop", client.peer, event.adu, too_soon)
                    event = client.framer.next_event()
                    continue
                if self.queued:
                    # Its turn on the bus; the requests behind it wait for its answer.
                    client.owed += 1
                    client.on_bus = True
                    self._jobs.put((client, event))
                    break
            reply = self.responder.answer(event, client.framer, client.peer)
            if reply:
                client.replied = time.monotonic() + self.faults.delay
                self._queue(client, reply)
            event = client.framer.next_event()
        self._flush(client)

    def _too_soon(self, client: _Client, now: float) -> str:
        """Why a request is dropped unanswered (--min-gap, --settle, --connection-requests), or ""."""
        if self.faults.connection_requests and client.requests > self.faults.connection_requests:
            return "past this connection's requests: dropped (--connection-requests)"
        if self.faults.settle and now - client.connected < self.faults.settle:
            return "request too soon after connecting: dropped (--settle)"
        if self.faults.min_gap and now - client.replied < self.faults.min_gap:
            return "request too soon after the last reply: dropped (--min-gap)"
        return ""

    def _queue(self, client: _Client, reply: bytes) -> None:
        if not self.faults.delay:
            client.out += reply  # sent by _flush once the whole read is answered
            return

        def send() -> None:
            client.owed -= 1
            if not client.closed:
                client.out += reply
                self._flush(client)

        client.owed += 1  # a reply the server owes is not the client's idleness
        self._later(time.monotonic() + self.faults.delay, send)

    def _flush(self, client: _Client) -> None:
        """Send what the socket takes now, never wait; read requests only while replies fit."""
        if client.closed:
            return
        if client.out:
            try:
                sent = client.sock.send(client.out)
            except (BlockingIOError, InterruptedError):
                sent = 0
            except OSError as error:
                self._close(client, error.strerror or str(error))
                return
            if sent:
                del client.out[:sent]
                client.last_active = time.monotonic()
        events = selectors.EVENT_READ if len(client.out) < OUT_LIMIT and not client.on_bus else 0
        if client.out:
            events |= selectors.EVENT_WRITE
        if events != client.events:
            client.events = events
            self.selector.modify(client.sock, events, client)

    def _expire(self, now: float) -> None:
        """Close the clients that completed no request and took no reply for idle_timeout,
        and those that completed none first_request_timeout after connecting."""
        if now - self._swept < TICK / 2:
            return
        self._swept = now
        first = self.first_request_timeout
        if first is not None:
            for client in [c for c in self._clients if not c.requests and now - c.connected > first]:
                why = (
                    f"first-request timeout: no whole request {now - client.connected:.1f} s after connecting"
                )
                if client.framer.buffered:
                    why += f", {client.framer.buffered} bytes of one buffered"
                self.stats.unused += 1
                self.stats.frame("close", client.peer, b"", why)
                self._close(client, why)
        limit = self.idle_timeout
        if limit is None:
            return
        for client in [c for c in self._clients if not c.owed and now - c.last_active > limit]:
            idle = f"{now - client.last_active:.1f} s"
            if client.out:
                why = f"idle timeout: took no reply for {idle}, {len(client.out)} bytes unsent"
            elif client.last_data > client.last_active:
                why = f"idle timeout: bytes but no whole request for {idle}"
                if client.framer.buffered:
                    why += f", {client.framer.buffered} bytes of one buffered"
            else:
                why = f"idle timeout: nothing received for {idle}"
            self.stats.expired += 1
            self.stats.frame("close", client.peer, b"", why)
            self._close(client, why)

    def _serve_tcp(self) -> None:
        while not self._stop:
            newcomers = False
            for key, mask in self.selector.select(self._wait(TICK)):
                client = key.data
                if client is None:
                    newcomers = True
                    continue
                if client is _WAKE:
                    self._collect()
                    continue
                if mask & selectors.EVENT_WRITE:
                    self._flush(client)
                if mask & selectors.EVENT_READ and not client.closed:
                    self._receive(client)
            if newcomers:
                # After the clients' reads: a request already on its way makes its client
                # busy or recently used before a newcomer looks for an idle slot.
                self._accept()
            self._send_due()
            now = time.monotonic()
            if self.framer_name != "tcp":
                # RTU/ASCII over TCP: no silence to see, but a long pause ends what is buffered.
                for client in list(self._clients):
                    if client.framer.buffered and not client.on_bus and now - client.last_data > TCP_GAP:
                        self._events(client, client.framer.silence)
            self._expire(now)
            self._tick()

    def _close_tcp(self) -> None:
        for client in list(self._clients):
            self._close(client, "server stopped")
        self.selector.close()
        self.listener.close()
        if self._worker is not None:
            self._jobs.put(None)
            # The transaction under way ends by its own deadline; a stop waits for it, not more.
            self._worker.join(WORKER_STOP)
            self._wake.close()
            self._waker.close()

    # -- queued answers (a bus behind the server) ----------------------------------------------

    def _work(self) -> None:
        """The worker thread: answer each queued request in turn, then wake the loop."""
        while (job := self._jobs.get()) is not None:
            client, event = job
            reply = None
            if not client.closed:  # a client gone while it waited is owed nothing
                try:
                    reply = self.responder.answer(event, client.framer, client.peer)
                except BaseException as error:  # a bug: the loop raises it, the worker ends
                    self._failure = error
            self._answered.append((client, reply))
            try:
                self._waker.send(b"!")
            except OSError:  # the buffer is full of wake-ups already, or the loop has closed
                pass
            if self._failure is not None:
                return

    def _collect(self) -> None:
        """The loop's side: hand the worker's answers to their clients."""
        try:
            self._wake.recv(RECV_SIZE)
        except OSError:
            pass
        if self._failure is not None:
            raise self._failure
        while self._answered:
            client, reply = self._answered.popleft()
            client.owed -= 1
            client.on_bus = False
            if client.closed:
                continue
            if reply:
                client.replied = time.monotonic()
                client.out += reply
            # Its next request, if one is buffered already, joins the back of the queue.
            self._events(client, client.framer.next_event)

    # -- serial ----------------------------------------------------------------------------

    def _open_serial(self) -> None:
        import serial

        from mbtool.link.transport import SerialTransport

        settings = self.settings
        transport = SerialTransport(self.target.path, settings)  # ConnectionFailed if it cannot
        self.transport = transport
        self._serial_error = serial.SerialException
        self.framer = device_framer(self.framer_name)
        self.stats.listening = f"{self.target.path} {settings}"
        self.stats.clients = 1

    def _serve_serial(self) -> None:
        t35 = silent_interval(self.baud, self.settings.char_bits)
        gap = max(t35, MIN_SERIAL_GAP) if self.framer_name == "rtu" else 1.0  # ASCII: 1 s between chars (§2)
        last_rx = 0.0
        peer = self.target.path
        while not self._stop:
            waiting = self.framer.buffered > 0
            try:
                data = self.transport.read(self._wait(min(gap, TICK) if waiting else TICK))
            except NoResponse as lost:  # the port went away (USB adapter unplugged)
                raise ConnectionFailed(f"lost the serial line: {lost}") from None
            now = time.monotonic()
            if data:
                last_rx = now
                self.framer.feed(data)
                events = self._drain(self.framer.next_event)
            elif waiting and now - last_rx >= gap:
                events = self._drain(self.framer.silence)
            else:
                events = []
            for event in events:
                reply = self.responder.answer(event, self.framer, peer)
                if reply:
                    # Keep the line quiet for t3.5 after the request before answering (spec §2).
                    due = max(now, last_rx + t35) + self.faults.delay
                    self._later(due, lambda reply=reply: self._write(reply))
            self._send_due()
            self._tick()

    def _drain(self, first: Callable[[], Frame | Rejected | None]) -> list[Frame | Rejected]:
        events = []
        event = first()
        while event is not None:
            events.append(event)
            event = self.framer.next_event()
        return events

    def _write(self, data: bytes) -> None:
        self.transport.write(data)

    # -- the loop ----------------------------------------------------------------------------

    def run(self, tick: Callable[[], None] | None = None) -> None:
        """Serve until stopped; ``tick`` is called after every turn of the loop (at most TICK apart)."""
        self._tick = tick or (lambda: None)
        try:
            if self.target.scheme == "tcp":
                self._serve_tcp()
            else:
                self._serve_serial()
        finally:
            self.close()

    def close(self) -> None:
        if self.target.scheme == "tcp":
            if hasattr(self, "selector"):
                self._close_tcp()
        elif hasattr(self, "transport"):
            self.transport.close()


class _Client:
    __slots__ = (
        "sock",
        "peer",
        "framer",
        "connected",
        "last_data",
        "last_active",
        "requests",
        "out",
        "owed",
        "events",
        "closed",
        "replied",
        "on_bus",
    )

    def __init__(self, sock: socket.socket, peer: str, framer: Framer) -> None:
        self.sock = sock
        self.peer = peer
        self.framer = framer
        self.connected = time.monotonic()
        self.last_data = self.connected  # the last bytes received (RTU/ASCII over TCP: the gap)
        self.last_active = self.connected  # connected, a whole request, or a reply taken
        self.requests = 0  # whole requests received
        self.out = bytearray()  # replies the socket has not taken yet
        self.owed = 0  # replies held back by --delay
        self.events = selectors.EVENT_READ
        self.closed = False
        self.replied = float("-inf")  # when the last reply went (--min-gap)
        self.on_bus = False  # a queued request of its is waiting for its answer
