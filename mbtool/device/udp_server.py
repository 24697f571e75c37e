"""The server behind ``serve`` and ``bridge`` on a UDP port (``mbtool.device.server`` picks it).

Modbus over UDP: each datagram is one request, MBAP (``udp://``) or an RTU or ASCII frame
(``rtu+udp://``, as serial device servers in UDP mode carry them), and its reply is one
datagram back to the address it came from.  A datagram is whole, so its end ends the frame:
one that is not a whole frame is logged and dropped, never joined to the next.

One ADU a datagram, as the spec's UDP mapping has it: the ADU at the datagram's start is
answered and whatever follows it is dropped and counted, never read as more requests.  A
sender's address is easily forged, so a datagram packed with requests would otherwise turn
one small packet into thousands of replies to someone else (and on ``bridge`` into minutes of
bus time that every other master waits behind).  The reply to a datagram is then at most one
ADU; ``rate`` (``--udp-rate``) also caps the datagrams answered a second for one source address.

There are no connections: nothing to accept, time out or refuse.  Answers that take a bus's
time (``bridge``) are given in turn, one at a time; the datagrams that come meanwhile wait in
the kernel's buffer, as they would at a device, and what it cannot hold is lost, as UDP
allows.
"""

from __future__ import annotations

import select
import socket
import time
from collections import OrderedDict

from mbtool.codec import framing
from mbtool.codec.framing import Rejected, device_framer
from mbtool.codec.pdu import MAX_PDU
from mbtool.device.serving import OUT_LIMIT, TICK, ServerParts, Serving, bind_port

DATAGRAMS_PER_TURN = 64  # read before the loop looks at the replies due
MAX_DATAGRAM = 65536
PEERS_COUNTED = 4096  # distinct peers remembered for the count (a flood of forged senders stops here)
SOURCES_LIMITED = 4096  # source addresses --udp-rate keeps a count for, the least recent forgotten


def longest_adu(framer_name: str) -> int:
    """The most bytes one ADU of this framing takes: what is read of a datagram."""
    if framer_name == "tcp":
        return framing.MBAP_HEADER + MAX_PDU
    if framer_name == "ascii":
        return framing.ASCII_MAX_CHARS
    return framing.RTU_MAX_ADU


class RateLimit:
    """At most ``rate`` datagrams a second from one source address, in bursts of as many (a
    token bucket an address, for the SOURCES_LIMITED addresses heard from last)."""

    def __init__(self, rate: float) -> None:
        self.rate = rate
        self._buckets: OrderedDict[str, tuple[float, float]] = OrderedDict()  # host -> (tokens, when)

    def allows(self, host: str, now: float) -> bool:
        tokens, then = self._buckets.pop(host, (self.rate, now))
        if len(self._buckets) >= SOURCES_LIMITED:
            self._buckets.popitem(last=False)
        tokens = min(self.rate, tokens + (now - then) * self.rate)
        allowed = tokens >= 1
        self._buckets[host] = (tokens - 1 if allowed else tokens, now)
        return allowed


class UdpServer(Serving):
    """Answers the datagrams that come to one UDP port."""

    def __init__(self, parts: ServerParts, rate: float | None = None) -> None:
        super().__init__(parts)
        self.framer = device_framer(parts.framer_name)
        self.longest = longest_adu(parts.framer_name)
        self.limit = RateLimit(rate) if rate else None
        self.sock: socket.socket | None = None  # once open
        self._peers: set[str] = set()
        self._limited: set[str] = set()  # sources past the rate now (logged once a run of drops)
        self._held = 0  # bytes of replies --delay holds back (at most OUT_LIMIT)

    def open(self) -> None:
        """Bind the port; ConnectionFailed (exit 6) if it cannot be."""
        self.sock, self.stats.listening = bind_port(self.target, socket.SOCK_DGRAM)

    def _serve(self) -> None:
        sock = self.sock
        assert sock is not None  # open() bound it
        while not self._stop:
            if select.select([sock], [], [], self._wait(TICK))[0]:
                for _ in range(DATAGRAMS_PER_TURN):
                    if self._stop:  # an answer may take a bus's time: a stop is not kept waiting
                        break
                    try:
                        data, sender = sock.recvfrom(MAX_DATAGRAM)
                    except (BlockingIOError, InterruptedError):
                        break
                    except OSError:  # an ICMP error for an earlier reply: that peer has gone
                        continue
                    self._datagram(data, sender)
            self._send_due()
            self._tick()

    def _datagram(self, data: bytes, sender) -> None:
        host, port = sender[:2]
        peer = f"[{host}]:{port}" if ":" in host else f"{host}:{port}"
        if peer not in self._peers and len(self._peers) < PEERS_COUNTED:
            self._peers.add(peer)
            self.stats.connections = len(self._peers)
        if self.limit is not None and not self._within_rate(self.limit, host, peer, data):
            return
        # One ADU a datagram: only as many bytes as the longest ADU can be its ADU, so a packed
        # datagram costs the framer no more than a single request does.
        framer = self.framer
        framer.reset()
        framer.feed(data[: self.longest])
        event = framer.silence()
        if event is None:
            return
        if isinstance(event, Rejected):
            # The datagram does not start with a frame: none of it is, whatever follows.
            event = Rejected(data[: self.longest], event.error)
            taken = len(data)
        else:
            taken = len(event.adu)
        if taken < len(data):
            self._drop_rest(data[taken:], peer)
        reply = self.responder.answer(event, framer, peer)
        if reply:
            self._reply(reply, sender, peer)

    def _drop_rest(self, rest: bytes, peer: str) -> None:
        why = f"{len(rest)} bytes after the datagram's ADU dropped (one ADU a datagram)"
        self.stats.trailing += 1
        self.stats.trailing_bytes += len(rest)
        self.stats.frame("--", peer, b"", why)
        self._log("drop", peer, rest[: self.longest], why)

    def _within_rate(self, limit: RateLimit, host: str, peer: str, data: bytes) -> bool:
        if limit.allows(host, time.monotonic()):
            self._limited.discard(host)
            return True
        self.stats.limited += 1
        if host not in self._limited and len(self._limited) < SOURCES_LIMITED:
            # Once a run of drops, not once a datagram: a flood would flood the log too.
            self._limited.add(host)
            why = f"past --udp-rate {limit.rate:g} a second from {host}: dropped until it slows"
            self.stats.frame("--", peer, b"", why)
            self._log("drop", peer, data[: self.longest], why)
        return False

    def _reply(self, reply: bytes, sender, peer: str) -> None:
        if not self.faults.delay:
            self._sendto(reply, sender)
            return
        if self._held >= OUT_LIMIT:
            why = "reply dropped: replies held back by --delay fill the output limit"
            self.stats.dropped += 1
            self.stats.frame("--", peer, reply, why)
            self._log("drop", peer, reply, why)
            return
        self._held += len(reply)

        def send() -> None:
            self._held -= len(reply)
            self._sendto(reply, sender)

        self._later(time.monotonic() + self.faults.delay, send)

    def _sendto(self, reply: bytes, sender) -> None:
        assert self.sock is not None  # open() bound it
        try:
            self.sock.sendto(reply, sender)
        except OSError:  # the kernel's buffer is full or the peer unreachable: a datagram lost
            pass

    def close(self) -> None:
        if self.sock is not None:
            self.sock.close()
