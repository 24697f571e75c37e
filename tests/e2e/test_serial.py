"""mbtool over a pseudo-terminal serial line (RTU and ASCII) and over socket:// (RTU over TCP),
with pymodbus's server on the other end.

Every mbtool run on a pty passes --parity N: Linux ptys reject PARENB (see tests/helpers/ptys.py).
"""

from __future__ import annotations

import json

import pytest
from helpers.checks import expect_ok, parse_hex_lines, plain_pairs
from helpers.devices import COILS, DISCRETE, HOLDING, start_device
from helpers.frames import crc16, lrc, rtu
from helpers.ptys import PTY_SERIAL_OPTS
from helpers.run import run_cli

pytestmark = pytest.mark.timeout(60)


def bit(b: bool) -> str:
    return "1" if b else "0"


@pytest.fixture(params=["rtu", "ascii"])
def serial_device(request, serial_rtu_device, serial_ascii_device):
    return serial_rtu_device if request.param == "rtu" else serial_ascii_device


def ser(dev, *args, **kw):
    extra = ["--framer", "ascii"] if dev.framer == "ascii" else []
    return run_cli(*args, "-p", dev.target, *PTY_SERIAL_OPTS, *extra, **kw)


def pymodbus_serial_client(dev):
    from pymodbus import FramerType
    from pymodbus.client import ModbusSerialClient

    c = ModbusSerialClient(
        dev.target, framer=FramerType(dev.framer), baudrate=19200, parity="N", timeout=1, retries=1
    )
    assert c.connect()
    return c


# ----------------------------------------------------------------------------- pty: RTU and ASCII


def test_serial_reads(serial_device):
    res = expect_ok(ser(serial_device, "read-holding-registers", "0", "10"))
    assert plain_pairs(res) == [(i, str(v)) for i, v in enumerate(HOLDING[:10])]
    res = expect_ok(ser(serial_device, "read-input-registers", "5", "3"))
    assert plain_pairs(res) == [(5, "205"), (6, "206"), (7, "207")]
    res = expect_ok(ser(serial_device, "read-coils", "0", "10"))
    assert plain_pairs(res) == [(i, bit(v)) for i, v in enumerate(COILS[:10])]
    res = expect_ok(ser(serial_device, "read-discrete-inputs", "0", "3"))
    assert plain_pairs(res) == [(i, bit(v)) for i, v in enumerate(DISCRETE[:3])]


def test_serial_unit_2(serial_device):
    res = expect_ok(ser(serial_device, "read-holding-registers", "2", "-u", "2", "-o", "json"))
    doc = json.loads(res.stdout)
    assert doc["unit"] == 2 and doc["values"] == [102]


def test_serial_writes_read_back(serial_device):
    expect_ok(ser(serial_device, "write-register", "200", "4321"))
    expect_ok(ser(serial_device, "write-register", "201", "-5"))
    expect_ok(ser(serial_device, "write-registers", "202", "7", "0x10", "65535"))
    expect_ok(ser(serial_device, "write-coil", "210", "on"))
    expect_ok(ser(serial_device, "write-coils", "211", "1", "0", "1"))
    back = expect_ok(ser(serial_device, "read-holding-registers", "200", "5"))
    assert plain_pairs(back) == [(200, "4321"), (201, "65531"), (202, "7"), (203, "16"), (204, "65535")]
    back = expect_ok(ser(serial_device, "read-coils", "210", "4"))
    assert plain_pairs(back) == [(210, "1"), (211, "1"), (212, "0"), (213, "1")]
    # independent check with pymodbus's serial client on the same line
    c = pymodbus_serial_client(serial_device)
    try:
        assert c.read_holding_registers(200, count=5, device_id=1).registers == [4321, 65531, 7, 16, 65535]
        assert c.read_coils(210, count=4, device_id=1).bits[:4] == [True, True, False, True]
    finally:
        c.close()


def test_serial_float32_cdab(serial_device):
    expect_ok(ser(serial_device, "write-registers", "220", "1.5", "--type", "float32", "--order", "CDAB"))
    raw = expect_ok(ser(serial_device, "read-holding-registers", "220", "2"))
    assert plain_pairs(raw) == [(220, "0"), (221, str(0x3FC0))]
    res = expect_ok(
        ser(serial_device, "read-holding-registers", "220", "1", "--type", "float32", "--order", "CDAB")
    )
    assert [(a, float(v)) for a, v in plain_pairs(res)] == [(220, 1.5)]


def test_serial_exception_02(serial_device):
    res = ser(serial_device, "read-holding-registers", "5000")
    assert res.returncode == 4, str(res)
    assert "02 Illegal Data Address" in res.stderr, str(res)
    assert "Traceback" not in res.stderr


def test_the_hex_trace_marks_an_exception_reply(serial_rtu_device):
    """pymodbus's device refuses address 5000: its RX line names the exception, as the error does."""
    res = ser(serial_rtu_device, "read-holding-registers", "5000", "--hex")
    assert res.returncode == 4, str(res)
    (rx,) = [h for h in parse_hex_lines(res.stderr) if h.direction == "RX"]
    assert rx.data[1:3] == bytes([0x83, 0x02]), str(res)
    assert rx.verdict.endswith("ok; exception 02 Illegal Data Address to FC 03 (0x03)"), str(res)


def test_rtu_hex_trace(serial_rtu_device):
    res = expect_ok(ser(serial_rtu_device, "read-holding-registers", "0", "10", "--hex"))
    assert plain_pairs(res) == [(i, str(v)) for i, v in enumerate(HOLDING[:10])], "stdout must stay clean"
    lines = parse_hex_lines(res.stderr)
    tx = [h for h in lines if h.direction == "TX"]
    rx = [h for h in lines if h.direction == "RX"]
    assert len(tx) == 1 and len(rx) == 1, str(res)
    # the contract's own example
    assert tx[0].raw.startswith("TX 01 03 00 00 00 0A C5 CD"), str(res)
    assert "CRC" in tx[0].verdict and "ok" in tx[0].verdict, str(res)
    assert "CRC" in rx[0].verdict and "ok" in rx[0].verdict, str(res)
    # independent check of the received frame
    frame = rx[0].data
    assert frame[:3] == bytes([1, 3, 20]) and frame[-2:] == crc16(frame[:-2]), str(res)
    assert frame == rtu(bytes([1, 3, 20]) + b"".join(v.to_bytes(2, "big") for v in HOLDING[:10]))
    # what actually went over the line is what was printed
    assert serial_rtu_device.pty.sent_by_mbtool(settle=0).endswith(tx[0].data)


def test_ascii_hex_trace_lrc_ok(serial_ascii_device):
    """--hex on ASCII: one TX and one RX line on stderr with an LRC verdict 'ok'; stdout clean."""
    res = expect_ok(ser(serial_ascii_device, "read-holding-registers", "0", "2", "--hex"))
    assert res.stdout == "0 100\n1 101\n"
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert [ln[:3] for ln in lines] == ["TX ", "RX "], str(res)
    for ln in lines:
        assert "LRC" in ln and "ok" in ln and "CRC" not in ln, str(res)
    # the request is ':010300000002' + LRC + CRLF on the wire
    body = bytes.fromhex("010300000002")
    wire = b":" + (body.hex() + f"{lrc(body):02x}").upper().encode() + b"\r\n"
    assert serial_ascii_device.pty.sent_by_mbtool(settle=0).endswith(wire)


def test_ascii_hex_trace_shows_the_frame_text(serial_ascii_device):
    """ASCII frames are text on the wire: the trace shows them as sent, colon to LRC."""
    res = expect_ok(ser(serial_ascii_device, "read-holding-registers", "0", "2", "--hex"))
    lines = [line for line in res.stderr.splitlines() if line.startswith(("TX ", "RX "))]
    assert lines == [
        "TX :010300000002FA  LRC FA ok",
        "RX :010304006400652F  LRC 2F ok",
    ], str(res)


def test_local_echo_is_stripped():
    """--echo: a half-duplex adapter hears its own frame before the reply (pty relay echoes it)."""
    with start_device(tcp=False, framer="rtu", units="1", pty_echo=True) as dev:
        res = expect_ok(
            run_cli("read-holding-registers", "0", "3", "-p", dev.target, *PTY_SERIAL_OPTS, "--echo")
        )
        assert plain_pairs(res) == [(0, "100"), (1, "101"), (2, "102")]
        res = expect_ok(run_cli("write-register", "230", "9", "-p", dev.target, *PTY_SERIAL_OPTS, "--echo"))
        assert plain_pairs(res) == [(230, "9")]


# ----------------------------------------------------------------------------- socket:// (RTU over TCP)


def sock(dev, *args, **kw):
    return run_cli(*args, "-p", dev.target, **kw)


def test_socket_reads(socket_rtu_device):
    res = expect_ok(sock(socket_rtu_device, "read-holding-registers", "0", "4"))
    assert plain_pairs(res) == [(0, "100"), (1, "101"), (2, "102"), (3, "103")]
    res = expect_ok(sock(socket_rtu_device, "read-input-registers", "19", "2"))
    assert plain_pairs(res) == [(19, "219"), (20, "0")]
    res = expect_ok(sock(socket_rtu_device, "read-coils", "0", "3"))
    assert plain_pairs(res) == [(0, "1"), (1, "0"), (2, "1")]
    res = expect_ok(sock(socket_rtu_device, "read-discrete-inputs", "18", "3"))
    assert plain_pairs(res) == [(18, "1"), (19, "1"), (20, "0")]


def test_socket_writes(socket_rtu_device, pymodbus_rtu_socket_client):
    c = pymodbus_rtu_socket_client
    expect_ok(sock(socket_rtu_device, "write-register", "400", "-2"))
    expect_ok(sock(socket_rtu_device, "write-registers", "401", "11", "12"))
    expect_ok(sock(socket_rtu_device, "write-coil", "400", "1"))
    expect_ok(sock(socket_rtu_device, "write-coils", "401", "0", "1", "1"))
    assert c.read_holding_registers(400, count=3, device_id=1).registers == [65534, 11, 12]
    assert c.read_coils(400, count=4, device_id=1).bits[:4] == [True, False, True, True]
    back = expect_ok(sock(socket_rtu_device, "read-holding-registers", "400", "3"))
    assert plain_pairs(back) == [(400, "65534"), (401, "11"), (402, "12")]


def test_socket_hex_crc_ok(socket_rtu_device):
    res = expect_ok(sock(socket_rtu_device, "read-holding-registers", "0", "10", "--hex"))
    lines = parse_hex_lines(res.stderr)
    assert [h.direction for h in lines] == ["TX", "RX"], str(res)
    assert lines[0].raw.startswith("TX 01 03 00 00 00 0A C5 CD"), str(res)
    for h in lines:
        assert "CRC" in h.verdict and "ok" in h.verdict, str(res)
        assert h.data[-2:] == crc16(h.data[:-2])


def test_socket_exception_02(socket_rtu_device):
    res = sock(socket_rtu_device, "read-coils", "5000", "8")
    assert res.returncode == 4, str(res)
    assert "02 Illegal Data Address" in res.stderr, str(res)


def test_closing_a_socket_bridge_does_not_sleep(monkeypatch):
    """pyserial's socket:// close sleeps 0.3 s; a one-shot command would pay it on every run."""
    import socket as sockets

    import serial.urlhandler.protocol_socket as bridge_module

    from mbtool.link.transport import SerialSettings, SerialTransport

    def no_sleep(seconds):
        raise AssertionError(f"close slept {seconds} s")

    with sockets.create_server(("127.0.0.1", 0)) as server:
        server.settimeout(5)
        transport = SerialTransport(f"socket://127.0.0.1:{server.getsockname()[1]}", SerialSettings())
        peer, _ = server.accept()
        monkeypatch.setattr(bridge_module.time, "sleep", no_sleep)
        transport.close()
        peer.settimeout(5)
        assert peer.recv(1) == b""  # the bridge saw the connection end
        assert not transport.port.is_open
        peer.close()


def test_a_setting_a_url_handler_does_not_support_is_one_cannot_open_error(monkeypatch):
    """pyserial raises NotImplementedError for a setting a port or url handler lacks
    (custom baud rates or RS-485 on some platforms, rfc2217:// and a write timeout): it is
    a port that cannot be opened as asked, one ConnectionFailed naming it (exit 6)."""
    import serial

    from mbtool.errors import ConnectionFailed, exit_code_for
    from mbtool.link.transport import SerialSettings, SerialTransport

    def refuse(url, **settings):
        raise NotImplementedError("non-standard baudrates are not supported on this platform")

    monkeypatch.setattr(serial, "serial_for_url", refuse)
    with pytest.raises(ConnectionFailed, match="^cannot open /dev/ttyFAKE: non-standard baudrates") as caught:
        SerialTransport("/dev/ttyFAKE", SerialSettings())
    assert int(exit_code_for(caught.value)) == 6
