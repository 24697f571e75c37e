"""rfc2217:// end to end: an RFC 2217 serial device server (pyserial's PortManager, as in its
examples/rfc2217_server.py) in front of a pseudo-terminal with pymodbus's RTU device behind it.

mbtool opens rfc2217://127.0.0.1:PORT, the server applies the baud rate and parity the
client asks for to its real port, and carries the RTU bytes both ways.
"""

from __future__ import annotations

import socket
import threading

import pytest
import serial
import serial.rfc2217
from helpers.checks import expect_ok, parse_hex_lines, plain_pairs
from helpers.ptys import PTY_SERIAL_OPTS
from helpers.run import run_mbtool


class _Writer:
    """PortManager writes its telnet replies with .write(), as pyserial's example Redirector has."""

    def __init__(self, connection: socket.socket) -> None:
        self.connection = connection

    def write(self, data: bytes) -> None:
        self.connection.sendall(data)


class _PtySerial(serial.Serial):
    """A pseudo-terminal has no modem lines (their ioctls fail): none to set, none to report."""

    def _update_dtr_state(self) -> None:
        pass

    def _update_rts_state(self) -> None:
        pass

    cts = dsr = ri = cd = property(lambda self: False)


class Rfc2217Bridge:
    """One client at a time, for the life of a test; every loop ends when the bridge stops."""

    def __init__(self, device_path: str) -> None:
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.listener.settimeout(0.2)
        self.port = self.listener.getsockname()[1]
        self.device_path = device_path
        self.stopping = threading.Event()
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()

    def _serve(self) -> None:
        while not self.stopping.is_set():
            try:
                connection, _ = self.listener.accept()
            except TimeoutError:
                continue
            with connection, _PtySerial(self.device_path, timeout=0.05, parity="N") as port:
                connection.settimeout(0.05)
                manager = serial.rfc2217.PortManager(port, _Writer(connection))
                self._pump(connection, port, manager)

    def _pump(self, connection: socket.socket, port, manager) -> None:
        while not self.stopping.is_set():
            try:
                data = connection.recv(1024)
                if not data:
                    return
                port.write(b"".join(manager.filter(data)))
            except TimeoutError:
                pass
            except OSError:
                return
            reply = port.read(port.in_waiting or 1)
            if reply:
                connection.sendall(b"".join(manager.escape(reply)))

    def close(self) -> None:
        self.stopping.set()
        self.thread.join(5)
        self.listener.close()


@pytest.fixture
def rfc2217_target(serial_rtu_device):
    bridge = Rfc2217Bridge(serial_rtu_device.target)
    try:
        yield f"rfc2217://127.0.0.1:{bridge.port}"
    finally:
        bridge.close()


def test_read_and_write_through_an_rfc2217_server(rfc2217_target):
    res = expect_ok(
        run_mbtool("read-holding-registers", "0", "3", "-p", rfc2217_target, *PTY_SERIAL_OPTS, "--hex")
    )
    assert plain_pairs(res) == [(0, "100"), (1, "101"), (2, "102")]
    assert [(line.direction, "ok" in line.verdict) for line in parse_hex_lines(res.stderr)] == [
        ("TX", True),
        ("RX", True),
    ]
    expect_ok(run_mbtool("write-register", "300", "4242", "-p", rfc2217_target, *PTY_SERIAL_OPTS))
    res = expect_ok(run_mbtool("read-holding-registers", "300", "-p", rfc2217_target, *PTY_SERIAL_OPTS))
    assert plain_pairs(res) == [(300, "4242")]
