"""Exit codes and error lines: 0 ok, 2 bad input (nothing sent), 3 timeout, 4 Modbus exception,
5 invalid response, 6 cannot open/connect.  Every error: exactly one 'mbtool: ' line on stderr,
never a traceback.
"""

from __future__ import annotations

import time

import pytest
from helpers.checks import assert_one_error_line, expect_ok, parse_hex_lines, plain_pairs
from helpers.frames import rtu
from helpers.ptys import PTY_SERIAL_OPTS
from helpers.run import run_cli, run_mbtool

pytestmark = pytest.mark.timeout(60)

# ----------------------------------------------------------------------------- 0


def test_exit_0(tcp_device):
    res = run_cli("read-holding-registers", "0", "-p", tcp_device.target)
    assert res.returncode == 0 and res.stderr == "", str(res)
    assert res.stdout == "0 100\n"


# ----------------------------------------------------------------------------- 2: bad input, nothing sent

BAD_INPUTS = {
    "quantity 0 registers": ["read-holding-registers", "0", "0"],
    "quantity 0 coils": ["read-coils", "0", "0"],
    "2001 coils": ["read-coils", "0", "2001"],
    "2001 discrete inputs": ["read-discrete-inputs", "0", "2001"],
    "126 holding registers": ["read-holding-registers", "0", "126"],
    "126 input registers": ["read-input-registers", "0", "126"],
    "63 float32 = 126 registers": ["read-holding-registers", "0", "63", "--type", "float32"],
    "1969 coils written": ["write-coils", "0", *["1"] * 1969],
    "124 registers written": ["write-registers", "0", *["1"] * 124],
    "address+count past 65536 (regs)": ["read-holding-registers", "65535", "2"],
    "address+count past 65536 (coils)": ["read-coils", "65530", "7"],
    "address+count past 65536 (write)": ["write-registers", "65535", "1", "2"],
    "address past 65535": ["read-holding-registers", "65536"],
    "unit 256": ["read-holding-registers", "0", "-u", "256"],
    "register value 65536": ["write-register", "0", "65536"],
    "register value -32769": ["write-register", "0", "-32769"],
    "registers value 70000": ["write-registers", "0", "1", "70000"],
    "bad number address 12x": ["read-holding-registers", "12x"],
    "bad number count 12x": ["read-holding-registers", "0", "12x"],
    "bad number value 12x": ["write-register", "0", "12x"],
    "bad number unit 12x": ["read-holding-registers", "0", "-u", "12x"],
    "timeout 0": ["read-holding-registers", "0", "-t", "0"],
    "timeout -1": ["read-holding-registers", "0", "-t", "-1"],
    "baud 0": ["read-holding-registers", "0", "--baud", "0"],
    "coil word maybe": ["write-coil", "0", "maybe"],
    "coil bit 2": ["write-coils", "0", "1", "2"],
    "missing address": ["read-holding-registers"],
    "unknown option": ["read-holding-registers", "0", "--bogus"],
}


@pytest.mark.parametrize("args", list(BAD_INPUTS.values()), ids=list(BAD_INPUTS))
def test_bad_input_exit_2_nothing_sent_tcp(silent_server, args):
    cmd, *rest = args
    # our -p/-t come first so that a bad -t in the case itself wins (last option wins)
    res = run_cli(cmd, "-p", silent_server.tcp_target, "-t", "0.3", *rest)
    assert_one_error_line(res, 2)
    assert silent_server.received_bytes() == b"", f"bytes were sent for bad input\n{res}"


@pytest.mark.parametrize(
    "args",
    [
        ["read-holding-registers", "0", "--baud", "0"],
        ["read-holding-registers", "0", "126"],
        ["write-register", "0", "65536"],
        ["read-coils", "0", "-u", "256"],
        ["read-input-registers", "0", "-t", "0"],
    ],
    ids=["baud 0", "126 registers", "value 65536", "unit 256", "timeout 0"],
)
def test_bad_input_exit_2_nothing_sent_serial(pty_pair, args):
    cmd, *rest = args
    res = run_cli(cmd, "-p", pty_pair.mbtool_path, *PTY_SERIAL_OPTS, "-t", "0.3", *rest)
    assert_one_error_line(res, 2)
    assert pty_pair.sent_by_mbtool() == b"", f"bytes reached the serial line for bad input\n{res}"


# The limits themselves are valid: these are sent (and the silent server lets them time out).
LIMITS_OK = {
    "2000 coils": ["read-coils", "0", "2000"],
    "125 registers": ["read-holding-registers", "0", "125"],
    "last address": ["read-holding-registers", "65535", "1"],
    "65535+1 coil": ["read-coils", "65535"],
    "1968 coils written": ["write-coils", "0", *["0"] * 1968],
    "123 registers written": ["write-registers", "65413", *["0"] * 123],
    "unit 255": ["read-holding-registers", "0", "-u", "255"],
    "value -32768": ["write-register", "0", "-32768"],
    "value 65535": ["write-register", "0", "65535"],
}


@pytest.mark.parametrize("args", list(LIMITS_OK.values()), ids=list(LIMITS_OK))
def test_limits_are_accepted_and_sent(silent_server, args):
    cmd, *rest = args
    res = run_cli(cmd, "-p", silent_server.tcp_target, "-t", "0.3", *rest)
    assert_one_error_line(res, 3)
    assert len(silent_server.received_bytes()) > 0


# ----------------------------------------------------------------------------- 3: no response


def test_silent_tcp_device_exit_3_quickly(silent_server):
    t0 = time.monotonic()
    res = run_mbtool("read-holding-registers", "0", "1", "-p", silent_server.tcp_target, "-t", "0.3")
    elapsed = time.monotonic() - t0
    assert_one_error_line(res, 3)
    assert elapsed < 2.0, f"took {elapsed:.2f}s with -t 0.3\n{res}"
    assert len(silent_server.received_bytes()) == 12  # one MBAP request was sent


def test_silent_socket_device_exit_3(silent_server):
    res = run_cli("read-coils", "0", "8", "-p", silent_server.socket_target, "-t", "0.3")
    assert_one_error_line(res, 3)
    assert silent_server.received_bytes() == rtu(bytes.fromhex("010100000008"))


def test_silent_serial_line_exit_3(pty_pair):
    t0 = time.monotonic()
    res = run_mbtool("read-holding-registers", "0", "-p", pty_pair.mbtool_path, *PTY_SERIAL_OPTS, "-t", "0.3")
    assert_one_error_line(res, 3)
    assert time.monotonic() - t0 < 2.0
    assert pty_pair.sent_by_mbtool() == rtu(bytes.fromhex("010300000001"))


def test_retries_resend_after_timeout(silent_server):
    res = run_mbtool(
        "read-holding-registers", "0", "-p", silent_server.tcp_target, "-t", "0.3", "--retries", "2"
    )
    assert_one_error_line(res, 3)
    assert len(silent_server.received_bytes()) == 3 * 12, "--retries 2 should send the request 3 times"
    assert res.elapsed < 4.0


# ----------------------------------------------------------------------------- 4: Modbus exception


def test_exception_02_tcp(tcp_device):
    res = run_cli("read-holding-registers", "5000", "-p", tcp_device.target)
    line = assert_one_error_line(res, 4)
    assert "02 Illegal Data Address" in line
    assert res.stdout == ""


def test_exception_from_raw_responder(raw_responder):
    srv = raw_responder(rtu(bytes.fromhex("018302")))
    res = run_cli("read-holding-registers", "0", "-p", srv.socket_target, "-t", "0.5")
    line = assert_one_error_line(res, 4)
    assert "02 Illegal Data Address" in line


# ----------------------------------------------------------------------------- 5: invalid response

GOOD_RTU_REPLY = rtu(bytes.fromhex("0103020064"))  # 1 register = 100


def test_raw_responder_control_good_reply(raw_responder):
    """Control: the raw responder with a correct reply makes mbtool succeed."""
    srv = raw_responder(GOOD_RTU_REPLY)
    res = expect_ok(run_cli("read-holding-registers", "0", "-p", srv.socket_target, "-t", "0.5"))
    assert plain_pairs(res) == [(0, "100")]


def corrupt_crc(frame: bytes) -> bytes:
    return frame[:-1] + bytes([frame[-1] ^ 0xFF])


INVALID_RTU_REPLIES = {
    "corrupted CRC": corrupt_crc(GOOD_RTU_REPLY),
    "wrong unit": rtu(bytes.fromhex("0203020064")),
    "wrong function": rtu(bytes.fromhex("0104020064")),
    "byte count does not match request": rtu(bytes.fromhex("010304006400 65".replace(" ", ""))),
}


@pytest.mark.parametrize("reply", list(INVALID_RTU_REPLIES.values()), ids=list(INVALID_RTU_REPLIES))
def test_invalid_rtu_response_exit_5(raw_responder, reply):
    srv = raw_responder(reply)
    t0 = time.monotonic()
    res = run_mbtool("read-holding-registers", "0", "-p", srv.socket_target, "-t", "0.3")
    assert_one_error_line(res, 5)
    assert time.monotonic() - t0 < 3.0


def test_an_rtu_over_tcp_gateway_read_as_modbus_tcp_is_named(raw_responder):
    """The commonest mix-up on site: tcp:// (MBAP) to a gateway that speaks RTU over TCP."""
    srv = raw_responder(GOOD_RTU_REPLY)
    res = run_cli("read-holding-registers", "0", "-p", srv.tcp_target, "-t", "0.3")
    line = assert_one_error_line(res, 5)
    assert "an RTU frame with a good CRC" in line and "--framer rtu" in line
    expect_ok(run_cli("read-holding-registers", "0", "-p", srv.tcp_target, "--framer", "rtu", "-t", "0.3"))


def test_a_bad_mbap_header_that_is_no_rtu_frame_gets_no_gateway_hint(raw_responder):
    srv = raw_responder(corrupt_crc(GOOD_RTU_REPLY))
    res = run_cli("read-holding-registers", "0", "-p", srv.tcp_target, "-t", "0.3")
    line = assert_one_error_line(res, 5)
    assert "MBAP protocol id" in line and "gateway" not in line


def test_corrupted_crc_hex_says_bad(raw_responder):
    """Contract: the RX line's checksum verdict contains "BAD" (and the error is one 'mbtool: ' line)."""
    srv = raw_responder(corrupt_crc(GOOD_RTU_REPLY))
    res = run_cli("read-holding-registers", "0", "-p", srv.socket_target, "-t", "0.5", "--hex")
    assert res.returncode == 5, str(res)
    assert "Traceback" not in res.stderr
    errors = [ln for ln in res.stderr.splitlines() if ln.startswith("mbtool: ")]
    assert len(errors) == 1, str(res)
    rx = [h for h in parse_hex_lines(res.stderr) if h.direction == "RX"]
    assert rx and "CRC" in rx[0].verdict and "BAD" in rx[0].verdict, str(res)


def test_corrupted_crc_hex_shows_the_frame_received(raw_responder):
    """The RX line carries the bytes that were received: the whole 7-byte reply, once."""
    srv = raw_responder(corrupt_crc(GOOD_RTU_REPLY))
    res = run_cli("read-holding-registers", "0", "-p", srv.socket_target, "-t", "0.5", "--hex")
    assert res.returncode == 5, str(res)
    rx = [h for h in parse_hex_lines(res.stderr) if h.direction == "RX"]
    assert b"".join(h.data for h in rx) == corrupt_crc(GOOD_RTU_REPLY), str(res)
    assert len(rx) == 1, str(res)


ASCII_GOOD = b":010302006496\r\n"  # LRC of 01 03 02 00 64 is 0x96
ASCII_BAD_LRC = b":010302006497\r\n"


def test_ascii_raw_responder_control_good_reply(raw_responder):
    srv = raw_responder(ASCII_GOOD)
    res = expect_ok(
        run_cli("read-holding-registers", "0", "-p", srv.socket_target, "--framer", "ascii", "-t", "0.5")
    )
    assert plain_pairs(res) == [(0, "100")]


def test_ascii_bad_lrc_exit_5(raw_responder):
    srv = raw_responder(ASCII_BAD_LRC)
    res = run_cli("read-holding-registers", "0", "-p", srv.socket_target, "--framer", "ascii", "-t", "0.5")
    assert_one_error_line(res, 5)


def test_ascii_bad_lrc_hex_says_bad(raw_responder):
    srv = raw_responder(ASCII_BAD_LRC)
    res = run_cli(
        "read-holding-registers", "0", "-p", srv.socket_target, "--framer", "ascii", "-t", "0.5", "--hex"
    )
    assert res.returncode == 5, str(res)
    rx = [ln for ln in res.stderr.splitlines() if ln.startswith("RX ")]
    assert rx and "LRC" in rx[0] and "BAD" in rx[0], str(res)


def _tcp_reply(tid_delta: int = 0, unit: int = 1, pdu: bytes = bytes.fromhex("03020064")):
    def reply(request: bytes) -> bytes:
        tid = (int.from_bytes(request[:2], "big") + tid_delta) & 0xFFFF
        return tid.to_bytes(2, "big") + b"\x00\x00" + (len(pdu) + 1).to_bytes(2, "big") + bytes([unit]) + pdu

    return reply


def test_tcp_raw_responder_control_good_reply(raw_responder):
    srv = raw_responder(_tcp_reply())
    res = expect_ok(run_cli("read-holding-registers", "0", "-p", srv.tcp_target, "-t", "0.5"))
    assert plain_pairs(res) == [(0, "100")]


@pytest.mark.parametrize(
    "reply_kw",
    [
        {"tid_delta": 1},
        {"unit": 7},
        {"pdu": bytes.fromhex("04020064")},
        {"pdu": bytes.fromhex("030400640065")},
    ],
    ids=["wrong transaction id", "wrong unit", "wrong function", "byte count"],
)
def test_invalid_tcp_response_exit_5(raw_responder, reply_kw):
    srv = raw_responder(_tcp_reply(**reply_kw))
    res = run_cli("read-holding-registers", "0", "-p", srv.tcp_target, "-t", "0.3")
    assert_one_error_line(res, 5)


# ----------------------------------------------------------------------------- 6: cannot open / connect


def test_refused_port_exit_6(refused_port):
    t0 = time.monotonic()
    res = run_mbtool("read-holding-registers", "0", "-p", f"tcp://127.0.0.1:{refused_port}", "-t", "0.5")
    assert_one_error_line(res, 6)
    assert time.monotonic() - t0 < 3.0


def test_refused_socket_port_exit_6(refused_port):
    res = run_cli("read-holding-registers", "0", "-p", f"socket://127.0.0.1:{refused_port}", "-t", "0.5")
    # pyserial's "Could not open port ...: [Errno 111]" wrapping is unwrapped: the port once, the reason
    assert assert_one_error_line(res, 6) == (
        f"mbtool: cannot open socket://127.0.0.1:{refused_port}: Connection refused"
    )


def test_missing_device_path_exit_6():
    res = run_cli("read-holding-registers", "0", "-p", "/dev/nonexistent-mbtool", "-t", "0.5")
    assert_one_error_line(res, 6)


def test_default_tcp_port_is_502(raw_responder):
    try:
        srv = raw_responder(_tcp_reply(), port=502)
    except OSError as exc:  # environment: cannot bind 502 (not root, or in use)
        pytest.skip(f"cannot bind 127.0.0.1:502 here: {exc}")
    res = expect_ok(run_cli("read-holding-registers", "0", "-p", "tcp://127.0.0.1", "-t", "0.5"))
    assert plain_pairs(res) == [(0, "100")]
    assert len(srv.received_bytes()) == 12


# ----------------------------------------------------------------------------- sim://


def test_sim_read_holding_registers():
    res = run_cli("read-holding-registers", "0", "5", "-p", "sim://")
    assert res.returncode == 0, str(res)
    assert len(res.lines) == 5, str(res)
    assert [a for a, _ in plain_pairs(res)] == [0, 1, 2, 3, 4]


def test_unreachable_network_host_does_not_hang():
    # a TEST-NET-1 address (RFC 5737) nobody answers: either times out (3) or cannot connect (6), quickly
    t0 = time.monotonic()
    res = run_mbtool("read-holding-registers", "0", "-p", "tcp://192.0.2.1:1502", "-t", "0.5")
    assert res.returncode in (3, 6), str(res)
    assert_one_error_line(res, res.returncode)
    assert time.monotonic() - t0 < 5.0, str(res)
