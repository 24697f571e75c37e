"""The server behind ``serve`` and ``bridge`` on a UDP port (``mbtool.device.server`` picks it).

Modbus over UDP: each datagram is one request, MBAP (``udp://``) or an RTU or ASCII frame
(``rtu+udp://``, as serial device servers in UDP mode carry them), and its reply is one
datagram back to the address it came from.  A datagram is whole, so its end ends the frame:
one that is not a whole frame is logged and dropped, never joined to the next.  There are
no connections: nothing to accept, time out or refuse, and no peer can hold another up,
since a datagram is answered (or dropped) as soon as it has been read.  Answers that take a
bus's time (``bridge``) are given in turn, one at a time; the datagrams that come meanwhile
wait in the kernel's buffer, as they would at a device, and what it cannot hold is lost,
as UDP allows.
"""

from __future__ import annotations

import select
import socket
import time

from mbtool.codec.framing import Frame, Rejected, device_framer
from mbtool.device.serving import OUT_LIMIT, TICK, ServerParts, Serving, bind_port

DATAGRAMS_PER_TURN = 64  # read before the loop looks at the stop flag and the replies due
MAX_DATAGRAM = 65536
PEERS_COUNTED = 4096  # distinct peers remembered for the count (a flood of forged senders stops here)


class UdpServer(Serving):
    """Answers the datagrams that come to one UDP port."""

    def __init__(self, parts: ServerParts) -> None:
        super().__init__(parts)
        self.framer = device_framer(parts.framer_name)
        self.sock: socket.socket | None = None  # once open
        self._peers: set[str] = set()
        self._held = 0  # bytes of replies --delay holds back (at most OUT_LIMIT)

    def open(self) -> None:
        """Bind the port; ConnectionFailed (exit 6) if it cannot be."""
        self.sock, self.stats.listening = bind_port(self.target, socket.SOCK_DGRAM)

    def _serve(self) -> None:
        while not self._stop:
            if select.select([self.sock], [], [], self._wait(TICK))[0]:
                for _ in range(DATAGRAMS_PER_TURN):
                    try:
                        data, sender = self.sock.recvfrom(MAX_DATAGRAM)
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
        framer = self.framer
        framer.reset()
        framer.feed(data)
        # The datagram is whole: what is left when its frames are out is no frame, and one
        # run of such bytes is one thing that went wrong, however the framer cut it up.
        events: list[Frame | Rejected] = []
        while (event := framer.silence()) is not None:
            if isinstance(event, Rejected) and events and isinstance(events[-1], Rejected):
                events[-1] = Rejected(events[-1].data + event.data, events[-1].error)
            else:
                events.append(event)
        for event in events:
            reply = self.responder.answer(event, framer, peer)
            if reply:
                self._reply(reply, sender, peer)

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
        try:
            self.sock.sendto(reply, sender)
        except OSError:  # the kernel's buffer is full or the peer unreachable: a datagram lost
            pass

    def close(self) -> None:
        if self.sock is not None:
            self.sock.close()
