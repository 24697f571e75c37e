"""What every transport shares (``mbtool.link.transport`` names it all again): the base class
the client talks to, the end of a connection, a TCP connection made, and an OS error in words.

Apart from ``transport`` so that the transports in modules of their own (``mbtool.link.tls``,
``mbtool.link.udp``), which ``transport.open_transport`` opens, import none of it back.
"""

from __future__ import annotations

import _socket
import os
import re
import time

from mbtool.errors import ConnectionFailed, NoResponse

WRITE_TIMEOUT = 5.0  # seconds a write may block before the port or peer counts as broken
READ_CHUNK = 65536  # bytes a read takes at most: what a burst of garbage and a reply may span
# The largest Modbus frame, an MBAP ADU (7 + 253; an RTU frame is 256): what a read that expects
# a reply takes at most.
FRAME_CHUNK = 260


class ConnectionClosed(NoResponse):
    """The peer closed the connection; no (further) reply can come."""


class Transport:
    """What the client needs of a link.  ``serial_line`` links keep t3.5 silences."""

    serial_line = True
    datagrams = False  # each read is one whole datagram (UDP): its end ends a frame
    description = ""

    def write(self, data: bytes) -> None:
        raise ConnectionFailed(f"{self.description}: not writable")

    def read(self, timeout: float) -> bytes:
        """Wait up to ``timeout`` seconds for bytes; return what arrived (b"" if none)."""
        time.sleep(max(timeout, 0))
        return b""

    def discard_input(self) -> bytes:
        """Drop (and return) bytes that arrived before a request: stale replies, noise."""
        return b""

    def input_waiting(self) -> bool:
        """Whether bytes have come that were not read yet (True where the link cannot tell)."""
        return True

    def close(self) -> None:
        """Release the link."""

    # Appended to "no response" and "closed the connection": what may explain them on this link.
    silence_hint = ""


def host_text(host: str) -> str:
    """A host as it goes before ``:PORT``: an IPv6 address in brackets (RFC 3986)."""
    return f"[{host}]" if ":" in host else host


def connect(host: str, port: int, timeout: float) -> _socket.socket:
    """A TCP connection to ``host:port`` (ConnectionFailed, exit 6, if there is none), Nagle
    off: a request is one small write that must leave at once.  Each address the name has is
    tried in turn, as socket.create_connection does, with the C module's socket: socket.py
    costs 14 M instructions (7% of a one-shot read: its enums) that a read over tcp:// need
    not pay (tls:// makes it the socket module's, which ssl wraps)."""
    try:
        # An ASCII host as bytes spares getaddrinfo the idna codec (~1.5 ms of imports).
        address = host.encode("ascii") if host.isascii() else host
        failed: OSError | None = None
        for family, kind, proto, _, where in _socket.getaddrinfo(address, port, 0, _socket.SOCK_STREAM):
            sock = _socket.socket(family, kind, proto)
            try:
                sock.settimeout(timeout)
                sock.connect(where)
            except OSError as error:
                sock.close()
                failed = error  # the last address's reason, as create_connection says it
                continue
            break
        else:
            raise failed or OSError(f"no address for {host}")
    except OSError as error:
        raise ConnectionFailed(f"cannot connect to {host}:{port}: {reason(error)}") from None
    sock.setsockopt(_socket.IPPROTO_TCP, _socket.TCP_NODELAY, 1)
    return sock


def _errno(error: BaseException) -> int | None:
    number = getattr(error, "errno", None)
    if number is None and error.args and isinstance(error.args[0], int):
        number = error.args[0]  # termios.error carries (errno, text) as plain args
    return number


def reason(error: BaseException) -> str:
    number = _errno(error)
    if isinstance(number, int) and number > 0:
        return os.strerror(number)
    text = getattr(error, "strerror", None) or str(error) or type(error).__name__
    text = text.split("\n")[0]
    if text.startswith("Could not open port "):
        # pyserial's wrapping repeats the port the message already names: keep its reason
        text = re.sub(r"^\[Errno -?\d+\] ", "", text.rsplit(": ", 1)[-1])
    return text
