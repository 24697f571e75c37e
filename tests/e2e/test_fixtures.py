"""Self-checks of the e2e harness, done with pymodbus's own client (no mbtool involved).

If these fail, the harness is broken, not mbtool.
"""

from __future__ import annotations

import socket
import time

import pytest
from helpers.devices import COILS, DISCRETE, HOLDING, INPUT
from helpers.frames import crc16, rtu

pytestmark = pytest.mark.timeout(30)


def test_crc16_known_vector():
    # The frame from the --hex contract example: 01 03 00 00 00 0A C5 CD
    assert crc16(bytes.fromhex("01030000000A")) == bytes.fromhex("C5CD")


def test_tcp_device_serves_the_data(pymodbus_tcp_client, tcp_device):
    c = pymodbus_tcp_client
    for unit in tcp_device.units:
        assert c.read_holding_registers(0, count=20, device_id=unit).registers == HOLDING
        assert c.read_input_registers(0, count=20, device_id=unit).registers == INPUT
        assert c.read_coils(0, count=20, device_id=unit).bits[:20] == COILS
        assert c.read_discrete_inputs(0, count=20, device_id=unit).bits[:20] == DISCRETE
    assert c.read_holding_registers(20, count=5, device_id=1).registers == [0] * 5
    assert c.read_holding_registers(999, count=1, device_id=1).registers == [0]
    r = c.read_holding_registers(5000, count=1, device_id=1)
    assert r.isError() and r.exception_code == 2


def test_socket_rtu_device(pymodbus_rtu_socket_client):
    c = pymodbus_rtu_socket_client
    assert c.read_holding_registers(0, count=3, device_id=1).registers == HOLDING[:3]
    assert c.read_coils(0, count=4, device_id=1).bits[:4] == COILS[:4]


@pytest.mark.parametrize("framer", ["rtu", "ascii"])
def test_serial_device_over_pty(framer, serial_rtu_device, serial_ascii_device):
    from pymodbus import FramerType
    from pymodbus.client import ModbusSerialClient

    dev = serial_rtu_device if framer == "rtu" else serial_ascii_device
    dev.pty.clear()  # the device is the session's: what earlier tests on this worker sent is not this test's
    c = ModbusSerialClient(
        dev.target, framer=FramerType(framer), baudrate=19200, parity="N", timeout=1, retries=1
    )
    assert c.connect()
    try:
        assert c.read_holding_registers(0, count=5, device_id=1).registers == HOLDING[:5]
        assert c.read_input_registers(3, count=2, device_id=2).registers == INPUT[3:5]
    finally:
        c.close()
    sent = dev.pty.sent_by_mbtool(settle=0)
    if framer == "rtu":
        assert sent.startswith(rtu(bytes.fromhex("010300000005")))
    else:
        assert sent.startswith(b":010300000005")


def test_silent_server_records_and_never_answers(silent_server):
    with socket.create_connection(("127.0.0.1", silent_server.port), timeout=2) as s:
        s.sendall(b"\x00\x01\x00\x00\x00\x06\x01\x03\x00\x00\x00\x01")
        s.settimeout(0.3)
        with pytest.raises(TimeoutError):
            s.recv(10)
    assert silent_server.received_bytes() == b"\x00\x01\x00\x00\x00\x06\x01\x03\x00\x00\x00\x01"


def test_raw_responder_and_refused_port(raw_responder, refused_port):
    srv = raw_responder(b"\x01\x03\x02\x00\x64\x00\x00")
    with socket.create_connection(("127.0.0.1", srv.port), timeout=2) as s:
        s.sendall(b"hello")
        s.settimeout(2)
        assert s.recv(100) == b"\x01\x03\x02\x00\x64\x00\x00"
    t0 = time.monotonic()
    with pytest.raises(ConnectionRefusedError):
        socket.create_connection(("127.0.0.1", refused_port), timeout=2)
    assert time.monotonic() - t0 < 1


def test_bare_pty_pair_is_silent(pty_pair):
    import os

    fd = os.open(pty_pair.mbtool_path, os.O_RDWR | os.O_NOCTTY)
    try:
        os.write(fd, b"\x01\x02")
    finally:
        os.close(fd)
    assert pty_pair.sent_by_mbtool() == b"\x01\x02"
