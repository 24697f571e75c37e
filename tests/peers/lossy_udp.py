"""A UDP proxy on loopback that loses and reorders datagrams, by a fixed pattern, both ways.

Between one client and one server: the client sends to ``proxy.port``, the proxy to the
server's port, and the server's datagrams go back to the client.  In each direction the
datagrams are counted, and of every ``drop_every`` one is never sent on, and of every
``hold_every`` one is held back: sent after the next datagram in that direction (the two
swap places), or ``hold_for`` seconds later if none comes (it arrives late).  The pattern is
fixed, so a run is the same every time; what happened is counted in ``dropped``, ``swapped``
and ``late``.  A thread does the work; ``close()`` stops it within a tenth of a second.
"""

from __future__ import annotations

import select
import socket
import threading
import time


class LossyUdpProxy:
    def __init__(
        self, server_port: int, drop_every: int = 5, hold_every: int = 7, hold_for: float = 0.4
    ) -> None:
        self.server = ("127.0.0.1", server_port)
        self.drop_every = drop_every
        self.hold_every = hold_every
        self.hold_for = hold_for
        self.front = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.front.bind(("127.0.0.1", 0))
        self.port = self.front.getsockname()[1]
        self.back = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.back.connect(self.server)
        self.client: tuple[str, int] | None = None
        self.counts = {"request": 0, "reply": 0}
        self.dropped = {"request": 0, "reply": 0}
        self.swapped = {"request": 0, "reply": 0}
        self.late = {"request": 0, "reply": 0}
        self._held: dict[str, tuple[float, bytes] | None] = {"request": None, "reply": None}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="lossy-udp", daemon=True)
        self._thread.start()

    @property
    def target(self) -> str:
        return f"127.0.0.1:{self.port}"

    def _send(self, direction: str, data: bytes) -> None:
        try:
            if direction == "request":
                self.back.send(data)
            elif self.client is not None:
                self.front.sendto(data, self.client)
        except OSError:  # the server has gone (port unreachable): a datagram lost like any other
            pass

    def _pass(self, direction: str, data: bytes) -> None:
        self.counts[direction] += 1
        number = self.counts[direction]
        if number % self.drop_every == 0:
            self.dropped[direction] += 1
            return
        held = self._held[direction]
        if number % self.hold_every == 0 and held is None:
            self._held[direction] = (time.monotonic() + self.hold_for, data)
            return
        self._send(direction, data)
        if held is not None:  # the held one goes after this one: the two have swapped places
            self._held[direction] = None
            self.swapped[direction] += 1
            self._send(direction, held[1])

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                ready, _, _ = select.select([self.front, self.back], [], [], 0.02)
            except (OSError, ValueError):
                return
            for sock in ready:
                try:
                    data, sender = sock.recvfrom(65536)
                except OSError:
                    continue
                if sock is self.front:
                    self.client = sender
                    self._pass("request", data)
                else:
                    self._pass("reply", data)
            now = time.monotonic()
            for direction, held in self._held.items():
                if held is not None and held[0] <= now:
                    self._held[direction] = None
                    self.late[direction] += 1
                    self._send(direction, held[1])

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2)
        self.front.close()
        self.back.close()
