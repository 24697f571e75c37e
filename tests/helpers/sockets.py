"""Misbehaving peers on 127.0.0.1, in threads of this process: a TCP server that never answers,
one that answers every request with bytes the test chooses (or hangs up), and free ports.
"""

from __future__ import annotations

import contextlib
import select
import socket
import threading
import time
from collections.abc import Callable


def free_port() -> int:
    """A TCP port on 127.0.0.1 nobody listens on right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def free_udp_port() -> int:
    """A UDP port on 127.0.0.1 nobody listens on right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


CLOSE = object()  # what a RawResponder's reply function returns to close the connection instead


class _ThreadServer:
    """A TCP listener on 127.0.0.1 handled in a thread; records every byte received."""

    def __init__(self, port: int = 0) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.sock.bind(("127.0.0.1", port))
        self.sock.listen(8)
        self.sock.settimeout(0.05)
        self.port = self.sock.getsockname()[1]
        self.received = bytearray()
        self.requests: list[bytes] = []  # one entry per recv() chunk
        self.connections = 0
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._conns: list[socket.socket] = []
        self._thread = threading.Thread(target=self._serve, daemon=True)
        self._thread.start()

    def answer(self, request: bytes) -> bytes | None:  # override
        return None

    def _serve(self) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = self.sock.accept()
            except TimeoutError:
                pass
            except OSError:
                return
            else:
                conn.setblocking(False)
                with self._lock:
                    self.connections += 1
                    self._conns.append(conn)
            conns = list(self._conns)
            if not conns:
                continue
            try:
                r, _, _ = select.select(conns, [], [], 0.02)
            except (OSError, ValueError):
                r = []
            for c in r:
                try:
                    data = c.recv(4096)
                except OSError:
                    data = b""
                if not data:
                    with self._lock:
                        self._conns.remove(c)
                    c.close()
                    continue
                with self._lock:
                    self.received += data
                    self.requests.append(bytes(data))
                reply = self.answer(bytes(data))
                if reply is CLOSE:  # the peer hangs up instead of answering
                    with self._lock:
                        self._conns.remove(c)
                    c.close()
                    continue
                if reply:
                    with contextlib.suppress(OSError):
                        c.sendall(reply)

    def received_bytes(self, settle: float = 0.1) -> bytes:
        time.sleep(settle)
        with self._lock:
            return bytes(self.received)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2)
        for c in self._conns:
            with contextlib.suppress(OSError):
                c.close()
        self.sock.close()


class SilentServer(_ThreadServer):
    """Accepts connections, reads everything, never answers."""

    @property
    def tcp_target(self) -> str:
        return f"tcp://127.0.0.1:{self.port}"

    @property
    def socket_target(self) -> str:
        return f"socket://127.0.0.1:{self.port}"


class RawResponder(SilentServer):
    """Answers every request with ``reply`` (bytes, or a function of the request bytes)."""

    def __init__(self, reply: bytes | Callable[[bytes], bytes], port: int = 0) -> None:
        self.reply = reply
        super().__init__(port)

    def answer(self, request: bytes) -> bytes | None:
        return self.reply(request) if callable(self.reply) else self.reply
