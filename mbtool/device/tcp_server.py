"""The server behind ``serve`` and ``bridge`` on a TCP port (``mbtool.device.server`` picks it).

* One thread, ``selectors`` over the listener and every client connection,
  each connection with its own framer (MBAP, or RTU/ASCII over TCP for masters
  that talk to serial device servers).  A client that sends bytes that are not
  MBAP is disconnected (what pymodbus and most devices do: after a bad header
  the stream cannot be resynchronised); the other clients never notice.
  No client can hold the others up or make memory grow: sockets never block,
  at most ``max_clients`` are served, each is read ``RECV_SIZE`` bytes a turn,
  its framer keeps at most one frame (the framers drop what cannot be one), its
  unsent replies, those --delay holds back included, are capped at ``OUT_LIMIT``
  (past it its requests are no longer read: the kernel's buffers and then the
  client's own sends take the back-pressure), and a client that completes no
  request and takes no reply for ``idle_timeout`` seconds is closed, so one that
  never sends, drips a byte a minute or never reads its replies gives its slot back.
* Nor can idle connections lock it: one that has completed no request
  ``first_request_timeout`` seconds after connecting is closed, and a newcomer
  past ``max_clients`` takes the slot of the least recently used idle client
  (nothing owed to it or unsent), one that never completed a request first
  (the Modbus TCP implementation guide's connection management: a server out of
  connections closes the oldest unused one).  Only when every client is busy is
  the newcomer closed at once.
* Queued answers (``queued``, for ``bridge``): an answer that takes a bus's time is given by
  a worker thread, one request at a time, while the loop goes on accepting, reading and
  sending.  Each client has at most one request waiting for the bus, and the next to go
  is that of the client that has used the least bus time lately (``_Turns``), so the
  clients take turns and one whose requests cost the bus its timeout waits behind those
  whose do not: none can hold the others up, however fast it sends.  While its request
  waits, a client's socket is read only for the start of its next ones (``RECV_SIZE``),
  so a client that leaves is seen to go, and its request never reaches the bus.
"""

from __future__ import annotations

import selectors
import socket
import threading
import time
from collections import deque
from collections.abc import Callable

from mbtool.codec.framing import Frame, Framer, Rejected, device_framer
from mbtool.device.serving import OUT_LIMIT, TICK, ServerParts, Serving, bind_port

TCP_GAP = 0.05  # RTU over TCP: a pause this long ends a frame whose length is unknown
MAX_CLIENTS = 64
IDLE_TIMEOUT = 60.0  # seconds without a whole request or a reply taken before a client is closed
FIRST_REQUEST_TIMEOUT = 5.0  # seconds from connecting to a first whole request
RECV_SIZE = 4096  # bytes read from one client per turn of the loop: the others get their turn
ACCEPTS_PER_TURN = 16  # a burst of connections cannot starve the clients already served
BUS_HALF_LIFE = 10.0  # seconds after which a client's bus time counts half, for whose turn it is
WORKER_STOP = 10.0  # seconds a stop waits for the queued answer under way
_WAKE = object()  # the selector's key for the worker's wake-ups


class TcpServer(Serving):
    """Serves the clients of one TCP port: ``max_clients`` at most, each closed after
    ``idle_timeout`` seconds idle, or ``first_request_timeout`` without a first request
    (None: never)."""

    def __init__(
        self,
        parts: ServerParts,
        *,
        queued: bool = False,
        max_clients: int = MAX_CLIENTS,
        idle_timeout: float | None = IDLE_TIMEOUT,
        first_request_timeout: float | None = FIRST_REQUEST_TIMEOUT,
    ) -> None:
        super().__init__(parts)
        # queued: answers take a bus's time, given one at a time by a worker thread.
        self.queued = queued
        self._turns = _Turns()
        self._answered: deque[tuple[_Client, bytes | None]] = deque()
        self._worker: threading.Thread | None = None
        self._failure: BaseException | None = None  # what stopped the worker, raised by the loop
        self.max_clients = max_clients
        self.idle_timeout = idle_timeout or None  # 0 or None: never
        self.first_request_timeout = first_request_timeout or None
        self._clients: set[_Client] = set()
        self._swept = 0.0
        self.selector: selectors.BaseSelector | None = None  # once open

    def open(self) -> None:
        """Bind the port; ConnectionFailed (exit 6) if it cannot be."""
        self.listener, self.stats.listening = bind_port(self.target, socket.SOCK_STREAM)  # tcp:// or tls://
        self.selector = selectors.DefaultSelector()
        self.selector.register(self.listener, selectors.EVENT_READ, None)
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
            client = _Client(self._wrap(conn), peer, device_framer(self.framer_name))
            assert self.selector is not None  # open() made it
            self.selector.register(client.sock, client.events, client)
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
        assert self.selector is not None  # open() made it
        self.selector.unregister(client.sock)
        client.sock.close()
        self._clients.discard(client)
        client.out.clear()
        self.stats.clients -= 1
        self._log("close", client.peer, b"", why)

    # -- the connection's bytes: a plain socket here, TLS in mbtool.device.tls_server ------------

    def _wrap(self, conn: socket.socket) -> socket.socket:
        """The socket a newly accepted connection is served through."""
        return conn

    def _recv(self, client: _Client) -> bytes:
        """What the client sent, at most RECV_SIZE; b"" at its end, BlockingIOError for nothing now."""
        return client.sock.recv(RECV_SIZE)

    def _send(self, client: _Client, data: bytearray) -> int:
        """Bytes of ``data`` the socket took now; BlockingIOError for none."""
        return client.sock.send(data)

    def _receive(self, client: _Client) -> None:
        try:
            data = self._recv(client)
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
        if client.on_bus:
            self._flush(client)  # its next requests wait in its framer for its answer
            return
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
                    # It waits for its turn on the bus; the requests behind it for its answer.
                    client.owed += 1
                    client.on_bus = True
                    self._turns.put(client, event)
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
            client.held -= len(reply)
            if not client.closed:
                client.out += reply
                self._flush(client)

        client.owed += 1  # a reply the server owes is not the client's idleness
        client.held += len(reply)  # counts towards OUT_LIMIT like the replies unsent
        self._later(time.monotonic() + self.faults.delay, send)

    def _flush(self, client: _Client) -> None:
        """Send what the socket takes now, never wait; read requests only while replies fit."""
        if client.closed:
            return
        if client.out:
            try:
                sent = self._send(client, client.out)
            except (BlockingIOError, InterruptedError):
                sent = 0
            except OSError as error:
                self._close(client, error.strerror or str(error))
                return
            if sent:
                del client.out[:sent]
                client.last_active = time.monotonic()
        # While its request waits for the bus, read on only until a request's worth is buffered:
        # enough to see the client close its connection, no more.
        room = not client.on_bus or client.framer.buffered < RECV_SIZE
        events = selectors.EVENT_READ if len(client.out) + client.held < OUT_LIMIT and room else 0
        if client.out:
            events |= selectors.EVENT_WRITE
        if events != client.events:
            client.events = events
            assert self.selector is not None  # open() made it
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

    def _serve(self) -> None:
        selector = self.selector
        assert selector is not None  # open() made it
        while not self._stop:
            newcomers = False
            for key, mask in selector.select(self._wait(TICK)):
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

    def close(self) -> None:
        if self.selector is None:
            return  # never opened
        for client in list(self._clients):
            self._close(client, "server stopped")
        self.selector.close()
        self.listener.close()
        if self._worker is not None:
            self._turns.close()
            # The transaction under way ends by its own deadline; a stop waits for it, not more.
            self._worker.join(WORKER_STOP)
            self._wake.close()
            self._waker.close()

    # -- queued answers (a bus behind the server) ----------------------------------------------

    def _work(self) -> None:
        """The worker thread: answer each waiting request in turn, then wake the loop."""
        while (job := self._turns.next()) is not None:
            client, event = job
            reply = None
            if not client.closed:  # a client gone while it waited is owed nothing
                started = time.monotonic()
                try:
                    reply = self.responder.answer(event, client.framer, client.peer)
                except BaseException as error:  # a bug: the loop raises it, the worker ends
                    self._failure = error
                client.use_bus(time.monotonic() - started)
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
            # Its next request, if one is buffered already, waits for its turn.
            self._events(client, client.framer.next_event)


class _Turns:
    """The requests waiting for the bus, at most one a client, and whose turn is next: that of
    the client with the least bus time lately, the one that came first among equals."""

    def __init__(self) -> None:
        self._waiting: list[tuple[_Client, Frame]] = []
        self._ready = threading.Condition()
        self._closed = False

    def put(self, client: _Client, event: Frame) -> None:
        with self._ready:
            self._waiting.append((client, event))
            self._ready.notify()

    def next(self) -> tuple[_Client, Frame] | None:
        """The next request to put on the bus (waits for one); None once closed."""
        with self._ready:
            while not self._waiting and not self._closed:
                self._ready.wait()
            if self._closed:
                return None
            now = time.monotonic()
            job = min(self._waiting, key=lambda job: job[0].bus_time(now))
            self._waiting.remove(job)
            return job

    def close(self) -> None:
        with self._ready:
            self._closed = True
            self._ready.notify()


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
        "held",
        "events",
        "closed",
        "replied",
        "on_bus",
        "bus",
        "bus_at",
        "tls",
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
        self.owed = 0  # replies held back by --delay, or waiting for the bus
        self.held = 0  # the bytes of those held back by --delay
        self.events = selectors.EVENT_READ
        self.closed = False
        self.replied = float("-inf")  # when the last reply went (--min-gap)
        self.on_bus = False  # a queued request of its is waiting for its answer
        self.bus = 0.0  # seconds of bus time it has used, decayed (BUS_HALF_LIFE)
        self.bus_at = self.connected  # when ``bus`` was last brought up to date
        self.tls = ""  # TLS (mbtool.device.tls_server): "handshake", "ready" or "refused"

    def bus_time(self, now: float) -> float:
        """The bus time it has used, each second counting half after BUS_HALF_LIFE."""
        return self.bus * 0.5 ** ((now - self.bus_at) / BUS_HALF_LIFE)

    def use_bus(self, seconds: float) -> None:
        now = time.monotonic()
        self.bus = self.bus_time(now) + seconds
        self.bus_at = now
