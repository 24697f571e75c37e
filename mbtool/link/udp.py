"""Modbus over UDP (``udp://HOST[:502]``, ``rtu+udp://HOST:PORT``): one ADU a datagram.

Modbus UDP carries the Modbus TCP ADU (MBAP) in a datagram of its own; serial device servers
in UDP mode carry RTU frames, CRC and all, the same way.  Nothing resends a lost datagram:
the client's timeout sees it, and ``--retries`` sends the request again.  A reply that comes
late, after its request was sent again, carries an earlier transaction id (MBAP), which the
client matches or drops; RTU frames carry none, so a late reply can only be told by its unit,
function and size, as on a serial line.

The socket is connected to the device, so the kernel drops datagrams from anyone else, and a
host that has nothing on the port says so (ICMP port unreachable): that is exit 6, as a
refused TCP connection is.
"""

from __future__ import annotations

import select
import socket

from mbtool.errors import ConnectionFailed
from mbtool.link.base import READ_CHUNK, Transport, host_text, reason

DISCARD_DATAGRAMS = 64  # stale datagrams dropped before a request, at most (a flood never ends)


class UdpTransport(Transport):
    serial_line = False
    datagrams = True  # a read is one datagram, whole: its end is the end of a frame

    def __init__(self, scheme: str, host: str, port: int) -> None:
        self.description = f"{scheme}://{host_text(host)}:{port}"
        try:
            family, kind, proto, _, address = socket.getaddrinfo(host, port, type=socket.SOCK_DGRAM)[0]
            self.sock = socket.socket(family, kind, proto)
        except OSError as error:
            raise ConnectionFailed(f"cannot reach {host}:{port}: {reason(error)}") from None
        try:
            self.sock.connect(address)  # no datagram leaves yet: this only names the peer
        except OSError as error:
            self.sock.close()
            raise ConnectionFailed(f"cannot reach {host}:{port}: {reason(error)}") from None
        self.sock.setblocking(False)

    def _unreachable(self) -> ConnectionFailed:
        return ConnectionFailed(f"nothing listens on {self.description} (the host says: port unreachable)")

    def write(self, data: bytes) -> None:
        try:
            self.sock.send(data)
        except ConnectionRefusedError:  # the ICMP answer to an earlier datagram
            raise self._unreachable() from None
        except BlockingIOError:  # the kernel's buffer is full: a datagram lost before it left
            pass
        except OSError as error:
            raise ConnectionFailed(f"cannot send to {self.description}: {reason(error)}") from None

    def read(self, timeout: float) -> bytes:
        try:
            if not select.select([self.sock], [], [], max(timeout, 0))[0]:
                return b""
            return self.sock.recv(READ_CHUNK)
        except BlockingIOError:
            return b""
        except ConnectionRefusedError:
            raise self._unreachable() from None
        except OSError as error:
            raise ConnectionFailed(f"{self.description}: {reason(error)}") from None

    def input_waiting(self) -> bool:
        try:
            return bool(select.select([self.sock], [], [], 0)[0])
        except (OSError, ValueError):
            return True

    def discard_input(self) -> bytes:
        stale = bytearray()
        for _ in range(DISCARD_DATAGRAMS):
            try:
                stale += self.sock.recv(READ_CHUNK)
            except OSError:  # none left (BlockingIOError), or the next read reports it
                break
        return bytes(stale)

    def close(self) -> None:
        self.sock.close()
