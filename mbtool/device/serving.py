"""What the server behind ``serve`` and ``bridge`` does whatever its transport.

* Who answers is pluggable (``Answerer``): the simulated device by default (``Responder``),
  or a gateway's forwarder (``mbtool.link.forward``, for ``mbtool bridge``).
* Faults of the I/O layer (``IoFaults``): ``Responder`` drops replies and corrupts their
  checksums (--drop, --corrupt) and bends Modbus TCP ones (--pad, --byte-count-off,
  --reply-unit); the transports delay them (--delay) and drop requests a picky device
  would (--min-gap, --settle, --connection-requests).
* ``Stats``: what the live view and the log show.
* ``bind_port``: the socket the TCP, TLS and UDP servers listen on, bound one way for all.
* ``Serving``: the loop both transports run (``mbtool.device.tcp_server``,
  ``mbtool.device.serial_server``): a stop flag, and replies held back until they are due.
  Every wait is bounded by ``TICK`` so a stop request (Ctrl-C, SIGTERM) is seen within a
  tenth of a second.
"""

from __future__ import annotations

import heapq
import random
import socket
import time
from abc import ABC, abstractmethod
from collections import deque
from collections.abc import Callable
from typing import Protocol

from mbtool.codec.framing import Frame, Framer, Rejected
from mbtool.codec.record import record, replace
from mbtool.device.device import Device
from mbtool.errors import ConnectionFailed
from mbtool.link.transport import Target

TICK = 0.1  # longest wait before the loop looks at the stop flag again
# Replies queued for a client that does not read them (TCP), or held back by --delay on a
# serial line; past this a TCP client's requests wait in the kernel.  One turn's read can
# still add a burst (at most 4096 / 8 requests of 260-byte replies, 133 KB), so a client
# costs at most about 200 KB.
OUT_LIMIT = 64 * 1024


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
        self.trailing = 0  # datagrams with bytes after their one ADU (UDP), and those bytes, dropped
        self.trailing_bytes = 0
        self.limited = 0  # datagrams dropped past the source's --udp-rate
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


@record
class ServerParts:
    """What every server is given, whatever its transport: where it serves, its framer's
    name, who answers, the I/O layer's faults it plays, its stats and its log."""

    target: Target
    framer_name: str
    answerer: Answerer
    faults: IoFaults
    stats: Stats
    log: Callable[[str, str, bytes, str], None]


def bind_port(target: Target, kind: int) -> tuple[socket.socket, str]:
    """A non-blocking socket of ``kind`` bound to the target's host and port (a stream one
    listening), and the target as bound, port 0 made the one the system gave: what the
    TCP, TLS and UDP servers listen on.  ConnectionFailed (exit 6) if it cannot be bound."""
    host, port = target.host, target.port
    try:
        family, _, proto, _, address = socket.getaddrinfo(host, port, type=kind, flags=socket.AI_PASSIVE)[0]
        sock = socket.socket(family, kind, proto)
    except OSError as error:
        raise ConnectionFailed(f"cannot listen on {host}:{port}: {error.strerror or error}") from None
    stream = kind == socket.SOCK_STREAM
    try:
        if stream:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind(address)
        if stream:
            # Room for a burst of connections: past max_clients they are accepted and closed
            # at once, which beats leaving them to time out on a full backlog.
            sock.listen(128)
    except OSError as error:
        sock.close()
        raise ConnectionFailed(f"cannot listen on {host}:{port}: {error.strerror or error}") from None
    sock.setblocking(False)
    bound = sock.getsockname()
    return sock, str(replace(target, host=bound[0], port=bound[1]))


class Serving(ABC):
    """The loop of a server on one transport: runs until ``stop()`` (called from a signal
    handler) or a fatal error on the port, then closes it.

    ``open``, ``_serve`` (one turn after another until ``_stop``, calling ``_tick`` after
    each) and ``close`` are the transport's."""

    def __init__(self, parts: ServerParts) -> None:
        self.target = parts.target
        self.framer_name = parts.framer_name
        self.responder = parts.answerer
        self.faults = parts.faults
        self.stats = parts.stats
        self._log = parts.log
        self._stop = False
        self._tick: Callable[[], None] = lambda: None
        self._pending: list[tuple[float, int, Callable[[], None]]] = []  # (due, seq, send)
        self._seq = 0

    @abstractmethod
    def open(self) -> None:
        """Bind the port or open the serial line; ConnectionFailed (exit 6) if it cannot be."""

    @abstractmethod
    def _serve(self) -> None:
        """The transport's loop: turn after turn until ``_stop``, ``_tick`` after each."""

    @abstractmethod
    def close(self) -> None:
        """Close the port or the line, and every client."""

    def stop(self) -> None:
        self._stop = True

    def run(self, tick: Callable[[], None] | None = None) -> None:
        """Serve until stopped; ``tick`` is called after every turn of the loop (at most TICK apart)."""
        self._tick = tick or (lambda: None)
        try:
            self._serve()
        finally:
            self.close()

    # -- replies held back until they are due (--delay; t3.5 on a serial line) ----------------

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
