"""``mbtool serve`` end to end: pymodbus's client and mbtool's own against it, over Modbus TCP,
RTU over TCP and pseudo-terminal serial pairs; bad clients; faults; signals; usage errors.

Every server here is a subprocess on a free loopback port (``tcp://127.0.0.1:0``: it prints
the port it got) or on a pty pair, and is stopped with SIGTERM at the end of its test.
"""

from __future__ import annotations

import contextlib
import os
import select
import signal
import socket
import struct
import subprocess
import time

import pytest
from helpers.checks import assert_one_error_line, expect_ok, plain_pairs
from helpers.frames import crc16
from helpers.ptys import PTY_SERIAL_OPTS, PtyPair
from helpers.run import run_cli, start_mbtool
from helpers.served import Served, pymodbus_tcp, serve
from helpers.sockets import free_port

pytestmark = pytest.mark.timeout(60)

READY = 10.0  # seconds for the live view to show its first screen


def mb(server_target: str, *args: str):
    """mbtool ARGS -p TARGET in this process (a client of serve needs no process of its own)."""
    return run_cli(*args, "-p", server_target)


# --- pymodbus's client against mbtool serve -----------------------------------------------


def _value(response) -> int:
    """A pymodbus diagnostics counter reply's value (an int, or a one-item list)."""
    message = response.message
    return message[0] if isinstance(message, list | tuple) else message


def exercise_every_function(client, unit: int = 1, variable: bool = True) -> None:
    """Every function code pymodbus can send, with the demo data (docs/simulator.md, "The built-in device")."""
    from pymodbus.pdu.file_message import FileRecord

    r = client.read_coils(0, count=5, device_id=unit)
    assert not r.isError() and r.bits[:5] == [True, False, True, False, True]
    r = client.read_discrete_inputs(0, count=4, device_id=unit)
    assert r.bits[:4] == [True, False, False, True]
    assert client.read_holding_registers(0, count=3, device_id=unit).registers == [0, 1, 2]
    assert client.read_input_registers(0, count=2, device_id=unit).registers == [1000, 1001]
    assert not client.write_coil(300, True, device_id=unit).isError()
    assert client.read_coils(300, count=1, device_id=unit).bits[0] is True
    assert not client.write_register(300, 4321, device_id=unit).isError()
    assert not client.write_coils(310, [True, False, True], device_id=unit).isError()
    assert client.read_coils(310, count=3, device_id=unit).bits[:3] == [True, False, True]
    assert not client.write_registers(301, [7, 8], device_id=unit).isError()
    assert client.read_holding_registers(300, count=3, device_id=unit).registers == [4321, 7, 8]
    assert not client.mask_write_register(
        address=300, and_mask=0x00F2, or_mask=0x0025, device_id=unit
    ).isError()
    assert client.read_holding_registers(300, count=1, device_id=unit).registers == [
        (4321 & 0xF2) | 0x25 & ~0xF2
    ]
    r = client.readwrite_registers(
        read_address=301, read_count=2, write_address=302, values=[99], device_id=unit
    )
    assert r.registers == [7, 99]  # the write is done before the read
    if variable:
        assert client.read_fifo_queue(address=200, device_id=unit).values == [0x0101, 0x0202, 0x0303]
    w = client.write_file_record(
        [FileRecord(file_number=4, record_number=7, record_data=b"\x06\xaf\x04\xbe")], device_id=unit
    )
    assert not w.isError()
    # pymodbus 3.16 takes a read's record_length in bytes (it sends record_length // 2 registers)
    r = client.read_file_record([FileRecord(file_number=4, record_number=7, record_length=4)], device_id=unit)
    assert r.records[0].record_data == b"\x06\xaf\x04\xbe"
    assert client.read_exception_status(device_id=unit).status == 0x6D
    r = client.report_device_id(device_id=unit)
    # spec §6: slave id, run indicator FF, extra bytes.  pymodbus reads the run indicator from
    # the last byte instead, so only its raw identifier bytes are compared.
    assert not r.isError() and r.identifier[:2] == bytes([unit, 0xFF])
    info = client.read_device_information(read_code=3, object_id=0, device_id=unit)
    assert info.information[0] == b"mbtool" and info.information[4] == b"mbtool serve"
    assert client.diag_query_data(b"\xa5\x37", device_id=unit).message == b"\xa5\x37"
    assert not client.diag_read_diagnostic_register(device_id=unit).isError()
    assert _value(client.diag_read_bus_message_count(device_id=unit)) > 0
    for call in (
        client.diag_read_bus_comm_error_count,
        client.diag_read_bus_exception_error_count,
        client.diag_read_device_message_count,
        client.diag_read_device_no_response_count,
        client.diag_read_device_nak_count,
        client.diag_read_device_busy_count,
        client.diag_read_bus_char_overrun_count,
        client.diag_read_iop_overrun_count,
        client.diag_clear_overrun_counter,
        client.diag_clear_counters,
    ):
        assert not call(device_id=unit).isError(), call.__name__
    if variable:  # Modbus Plus statistics: clear is an echo, get 0003, 6C, 54 words (spec §4)
        assert not client.diag_getclear_modbus_response(data=4, device_id=unit).isError()
        assert not client.diag_getclear_modbus_response(data=3, device_id=unit).isError()
    assert not client.diag_change_ascii_input_delimeter(delimiter=0x0A, device_id=unit).isError()
    r = client.diag_get_comm_event_counter(device_id=unit)
    assert not r.isError() and r.count > 0
    r = client.diag_get_comm_event_log(device_id=unit)
    assert not r.isError() and r.events


def test_pymodbus_tcp_every_function_code():
    with serve() as server:
        client = pymodbus_tcp(server)
        try:
            exercise_every_function(client)
            # exceptions, as pymodbus sees them
            r = client.read_holding_registers(65535, count=2)
            assert r.isError() and r.exception_code == 2
        finally:
            client.close()


def test_pymodbus_tcp_several_units_and_unit_0():
    with serve("-u", "1-3,17") as server:
        assert "units 1-3,17" in server.first_line
        client = pymodbus_tcp(server)
        try:
            client.write_register(50, 77, device_id=2)
            # Unit 0 on Modbus TCP is the device itself (the lowest unit), answered, no
            # broadcast; test_fidelity_device.py has the broadcast with RTU framing.
            assert not client.write_register(51, 5, device_id=0).isError()
            for unit in (1, 2, 3, 17):
                regs = client.read_holding_registers(50, count=2, device_id=unit).registers
                assert regs == [77 if unit == 2 else 50, 5 if unit == 1 else 51], unit
            assert client.report_device_id(device_id=17).identifier[:2] == b"\x11\xff"
        finally:
            client.close()
        # a unit not served stays silent
        res = mb(server.target, "read-holding-registers", "0", "-u", "4", "-t", "0.3")
        assert res.returncode == 3, str(res)


def test_many_concurrent_clients():
    with serve() as server:
        clients = [pymodbus_tcp(server) for _ in range(8)]
        try:
            for round_ in range(5):
                for i, client in enumerate(clients):
                    client.write_register(400 + i, round_ * 10 + i)
                for i, client in enumerate(clients):
                    assert client.read_holding_registers(400 + i, count=1).registers == [round_ * 10 + i]
        finally:
            for client in clients:
                client.close()


@pytest.mark.parametrize("framer", ["rtu", "ascii"])
def test_pymodbus_serial_every_function_code(framer):
    from pymodbus import FramerType
    from pymodbus.client import ModbusSerialClient

    pair = PtyPair()
    try:
        with serve("--framer", framer, "--parity", "N", target=pair.device_path) as server:
            assert server.target == pair.device_path
            kind = FramerType.RTU if framer == "rtu" else FramerType.ASCII
            client = ModbusSerialClient(pair.mbtool_path, framer=kind, baudrate=19200, timeout=2, retries=0)
            assert client.connect()
            try:
                # pymodbus 3.16's RTU framer cannot size an FC24 reply (its byte count is 2 bytes)
                # nor any Modbus Plus (FC08 sub 15) reply, and times out; the server's replies are
                # checked byte by byte in test_device.py.
                exercise_every_function(client, variable=framer != "rtu")
            finally:
                client.close()
    finally:
        pair.close()


def test_listen_only_sequence_over_serial():
    """Spec §4/§5: force listen-only, a read gets no reply, restart comms, the log shows both."""
    from pymodbus.client import ModbusSerialClient
    from pymodbus.exceptions import ModbusIOException

    pair = PtyPair()
    try:
        with serve("--parity", "N", target=pair.device_path):
            client = ModbusSerialClient(pair.mbtool_path, baudrate=19200, timeout=0.5, retries=0)
            assert client.connect()
            try:
                client.diag_force_listen_only()  # no response expected
                time.sleep(0.05)
                with pytest.raises(ModbusIOException):  # silence: no reply
                    client.read_holding_registers(0, count=1)
                client.diag_restart_communication(False, no_response_expected=True)  # no reply either
                time.sleep(0.05)
                assert client.read_holding_registers(0, count=1).registers == [0]
                log = client.diag_get_comm_event_log()
                events = list(log.events)
                assert 0x04 in events and 0x00 in events
                assert events.index(0x00) < events.index(0x04)  # newest first: restart, then listen-only
                assert 0xA0 in events  # the read heard in listen-only mode
                assert _value(client.diag_read_device_no_response_count()) >= 1
            finally:
                client.close()
    finally:
        pair.close()


# --- mbtool's own client against mbtool serve ----------------------------------------------


def test_mbtool_client_over_tcp():
    with serve() as server:
        res = expect_ok(mb(server.target, "read-holding-registers", "100", "1", "--type", "float32"))
        assert plain_pairs(res) == [(100, "21.5")]
        expect_ok(mb(server.target, "write-registers", "10", "5", "6"))
        assert plain_pairs(expect_ok(mb(server.target, "read-holding-registers", "10", "2"))) == [
            (10, "5"),
            (11, "6"),
        ]
        expect_ok(mb(server.target, "write-coils", "20", "1", "1", "0"))
        assert plain_pairs(expect_ok(mb(server.target, "read-coils", "20", "3"))) == [
            (20, "1"),
            (21, "1"),
            (22, "0"),
        ]
        res = mb(server.target, "read-input-registers", "65535", "2")
        assert res.returncode == 2  # refused before sending
        res = mb(server.target, "read-discrete-inputs", "0", "3")
        assert plain_pairs(expect_ok(res)) == [(0, "1"), (1, "0"), (2, "0")]


@pytest.mark.parametrize("framer", ["rtu", "ascii"])
def test_mbtool_client_serial_line_over_tcp(framer):
    """RTU/ASCII framing over a TCP listener: what a master sees through a serial device server."""
    with serve("--framer", framer, quiet=False) as server:
        res = expect_ok(
            mb(server.socket_target, "read-holding-registers", "0", "3", "--framer", framer, "--hex")
        )
        assert plain_pairs(res) == [(0, "0"), (1, "1"), (2, "2")]
        assert "ok" in res.stderr
        expect_ok(mb(server.socket_target, "write-register", "9", "99", "--framer", framer))
        code, out, _ = server.stop()
        assert code == 0
        # the log shows frames as they are on the wire: ASCII as text, RTU as hex
        shown = ":010300000003F9\\r\\n" if framer == "ascii" else "RX 01 03 00 00 00 03 05 CB"
        assert shown in out, out


def test_mbtool_client_over_serial_rtu():
    pair = PtyPair()
    try:
        with serve("--parity", "N", "-u", "5", target=pair.device_path):
            args = ("-u", "5", *PTY_SERIAL_OPTS)
            expect_ok(run_cli("write-register", "3", "333", "-p", pair.mbtool_path, *args))
            res = expect_ok(run_cli("read-holding-registers", "2", "2", "-p", pair.mbtool_path, *args))
            assert plain_pairs(res) == [(2, "2"), (3, "333")]
            # a frame for another unit on the bus is ignored: no reply, so a timeout
            res = run_cli(
                "read-holding-registers",
                "0",
                "-p",
                pair.mbtool_path,
                "-u",
                "6",
                "-t",
                "0.3",
                *PTY_SERIAL_OPTS,
            )
            assert res.returncode == 3, str(res)
    finally:
        pair.close()


# --- bad clients never hurt the server or the other clients -------------------------------


def _raw(server: Served) -> socket.socket:
    s = socket.create_connection((server.host, server.port), timeout=2)
    s.settimeout(2)
    return s


def _mbap(tid: int, unit: int, pdu: bytes) -> bytes:
    return struct.pack(">HHHB", tid, 0, len(pdu) + 1, unit) + pdu


def test_bad_requests_over_tcp():
    with serve() as server:
        good = pymodbus_tcp(server)
        try:
            with _raw(server) as s:
                s.sendall(_mbap(1, 1, b"\x41"))  # unknown function code
                assert s.recv(100) == _mbap(1, 1, b"\xc1\x01")
                s.sendall(_mbap(2, 1, bytes.fromhex("0300000000")))  # quantity 0
                assert s.recv(100) == _mbap(2, 1, b"\x83\x03")
                s.sendall(_mbap(3, 1, bytes.fromhex("0300")))  # truncated PDU in a whole MBAP frame
                assert s.recv(100) == _mbap(3, 1, b"\x83\x03")
            assert good.read_holding_registers(0, count=1).registers == [0]
            with _raw(server) as s:
                s.sendall(struct.pack(">HHHB", 4, 0, 2000, 1) + b"\x03" * 50)  # oversized MBAP length
                assert s.recv(100) == b""  # the server hangs up on a stream it cannot resynchronise
            with _raw(server) as s:
                s.sendall(b"\x00\x05\x00\x00")  # a truncated header, then the client leaves
            with _raw(server) as s:
                s.sendall(os.urandom(3000))
                with contextlib.suppress(ConnectionResetError):
                    s.recv(100)
            assert good.read_holding_registers(1, count=1).registers == [1]
        finally:
            good.close()


def test_bad_frames_over_rtu_tcp():
    with serve("--framer", "rtu") as server:
        with _raw(server) as s:
            request = bytes.fromhex("010300000001")
            s.sendall(request + b"\x00\x00")  # bad CRC: ignored like on a bus
            s.sendall(b"\x01\x03\x00")  # a truncated frame, ended by the pause that follows
            time.sleep(0.2)
            s.sendall(request + crc16(request))
            reply = s.recv(100)
            assert reply == bytes.fromhex("01030200 00".replace(" ", "")) + crc16(bytes.fromhex("0103020000"))
            unknown = bytes.fromhex("0141")
            s.sendall(unknown + crc16(unknown))  # unknown function code: answered 01 after silence
            body = bytes.fromhex("01C101")
            assert s.recv(100) == body + crc16(body)
            s.sendall(bytes.fromhex("01080000000C0000".replace(" ", ""))[:2])  # junk
            time.sleep(0.2)
            query = bytes.fromhex("0108000C0000")  # CRC error count
            s.sendall(query + crc16(query))
            reply = s.recv(100)
            assert reply[:4] == bytes.fromhex("0108000C") and int.from_bytes(reply[4:6], "big") >= 1


# --- faults ---------------------------------------------------------------------------------


def test_fault_exception_and_delay():
    with serve("--exception", "3:2", "--exception", "0x06:0x04", "--delay", "0.3") as server:
        res = mb(server.target, "read-holding-registers", "0")
        assert res.returncode == 4 and "exception 02" in res.stderr, str(res)
        res = mb(server.target, "write-register", "0", "1")
        assert res.returncode == 4 and "exception 04" in res.stderr, str(res)
        t0 = time.monotonic()
        expect_ok(mb(server.target, "read-input-registers", "0"))
        assert time.monotonic() - t0 >= 0.3


def test_fault_busy_then_ready():
    with serve("--busy", "1.5") as server:
        res = mb(server.target, "read-holding-registers", "0")
        assert res.returncode == 4 and "exception 06" in res.stderr, str(res)
        time.sleep(1.6)
        expect_ok(mb(server.target, "read-holding-registers", "0"))


def test_fault_drop_and_corrupt():
    with serve("--drop", "1") as server:
        res = mb(server.target, "read-holding-registers", "0", "-t", "0.3")
        assert res.returncode == 3, str(res)
    with serve("--framer", "rtu", "--corrupt", "1") as server:
        res = mb(server.socket_target, "read-holding-registers", "0", "-t", "0.5", "--hex")
        assert res.returncode == 5 and "CRC" in res.stderr, str(res)
    with serve("--framer", "ascii", "--corrupt", "1", "--seed", "1") as server:
        res = mb(server.socket_target, "read-holding-registers", "0", "-t", "0.5", "--framer", "ascii")
        assert res.returncode == 5 and "LRC" in res.stderr, str(res)


# --- data file, output modes, signals, usage errors ------------------------------------------


def test_data_file_toml(tmp_path):
    path = tmp_path / "plant.toml"
    path.write_text('[holding_registers]\n0 = [11, 22]\n[identity]\nvendor_name = "ACME"\n')
    with serve("--data", str(path)) as server:
        res = expect_ok(mb(server.target, "read-holding-registers", "0", "3"))
        assert plain_pairs(res) == [(0, "11"), (1, "22"), (2, "0")]
        client = pymodbus_tcp(server)
        try:
            assert client.read_device_information(read_code=1).information[0] == b"ACME"
        finally:
            client.close()


def test_log_mode_prints_frames_and_sigint_exits_0():
    with serve(quiet=False) as server:
        expect_ok(mb(server.target, "read-holding-registers", "0"))
        code, out, err = server.stop(signal.SIGINT)
        assert code == 0, err
        assert " RX 00 01 00 00 00 06 01 03 00 00 00 01" in out
        assert " TX 00 01 00 00 00 05 01 03 02 00 00" in out
        assert "stopped: 1 request, 1 reply" in out


class LiveView:
    """``mbtool serve`` with its stdout on a terminal (a pty): the live view."""

    def __init__(self, master: int, proc: subprocess.Popen, port: int) -> None:
        self.master = master
        self.proc = proc
        self.target = f"tcp://127.0.0.1:{port}"
        self.port = port
        self.seen = b""

    def until(self, text: bytes, wait: float = 5.0) -> bool:
        """Read the terminal until ``text`` shows (or ``wait`` seconds pass); the screen is
        read all along, so the server never waits on a full terminal."""
        end = time.monotonic() + wait
        while time.monotonic() < end and text not in self.seen and self.proc.poll() is None:
            ready, _, _ = select.select([self.master], [], [], 0.1)
            if ready:
                with contextlib.suppress(OSError):
                    self.seen += os.read(self.master, 65536)
        return text in self.seen


@contextlib.contextmanager
def live_view(*args: str):
    master, slave = os.openpty()
    port = free_port()
    env = {"COLUMNS": "120", "LINES": "40", "TERM": "xterm"}
    proc = start_mbtool("serve", "-p", f"tcp://127.0.0.1:{port}", *args, env=env, stdout=slave, stderr=slave)
    os.close(slave)
    try:
        view = LiveView(master, proc, port)
        assert view.until(b"FC08 counters", READY), view.seen[-2000:]
        yield view
        proc.send_signal(signal.SIGTERM)
        view.until(b"\0", 0.5)  # drain what it prints as it stops
        assert proc.wait(timeout=5) == 0, view.seen[-2000:]
        assert b"Traceback" not in view.seen, view.seen[-2000:]
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=5)
        os.close(master)


def test_live_view_on_a_terminal():
    with live_view() as view:
        expect_ok(run_cli("read-coils", "0", "-p", view.target))
        assert view.until(b"01 01 00 00 00 01")  # the request in "last frames"


def test_live_view_shows_what_a_peer_sends_as_text_never_as_markup():
    """Issue 29 item 5: one ASCII frame with rich markup in it stopped serve (MarkupError)."""
    with live_view("--framer", "ascii") as view:
        with socket.create_connection(("127.0.0.1", view.port), timeout=5) as hostile:
            # Shown as the characters they are in "last frames" (CR LF as \\r\\n); each is
            # sent once the one before is shown, so each is a frame of its own.
            hostile.sendall(b":[/bogus]\r\n")
            assert view.until(b":[/bogus]\\r\\n"), view.seen[-2000:]
            hostile.sendall(b":[bold]01[/bold]\r\n")
            assert view.until(b":[bold]01[/bold]\\r\\n"), view.seen[-2000:]
            hostile.sendall(b":\x1b]0;pwned\x07\r\n")  # a terminal's escape: set the title
            assert view.until(b"3A 1B 5D 30 3B 70 77 6E 65 64 07"), view.seen[-2000:]  # in hex
        assert b"\x1b]0;" not in view.seen
        assert view.proc.poll() is None, view.seen[-2000:]
        request = b"\x01\x03\x00\x07\x00\x01"
        frame = b":" + (request + bytes([(-sum(request)) & 0xFF])).hex().upper().encode() + b"\r\n"
        with socket.create_connection(("127.0.0.1", view.port), timeout=5) as good:
            good.sendall(frame)
            assert good.recv(100).startswith(b":0103020007")


@pytest.mark.parametrize(
    ("args", "code", "text"),
    [
        (("-u", "0"), 2, "unit 0"),
        (("-u", "5-2"), 2, "backwards"),
        (("-u", "x"), 2, "not a number"),
        (("--exception", "3"), 2, "FC:CODE"),
        (("--drop", "2"), 2, "between 0 and 1"),
        (("--corrupt", "0.5"), 2, "MBAP"),
        (("-p", "/dev/ttyS0", "--bytesize", "7"), 2, "8 data bits"),
        (("--data", "/nonexistent/plant.toml"), 2, "cannot read"),
        (("-p", "/dev/nonexistent-tty"), 6, "cannot open"),
        (("-p", "/dev/nonexistent-tty", "--framer", "tcp"), 2, "tcp://"),
        (("-p", "tcp://127.0.0.1:99999"), 2, "bad port 99999"),
        (("-p", "sim://"), 2, "sim://"),
    ],
)
def test_usage_errors(args, code, text):
    res = run_cli("serve", *args)
    line = assert_one_error_line(res, code)
    assert text in line


def test_port_in_use_is_exit_6():
    with serve() as server:
        res = run_cli("serve", "-p", f"tcp://127.0.0.1:{server.port}", "-q")
        line = assert_one_error_line(res, 6)
        assert "cannot listen" in line


def test_garbage_stream_over_rtu_tcp_does_not_stop_the_server():
    with serve("--framer", "rtu") as server:
        with _raw(server) as s:
            s.sendall(b"\xff" * 5000 + bytes(range(256)) * 4)
            time.sleep(0.2)
            request = bytes.fromhex("010300010001")
            s.sendall(request + crc16(request))
            body = bytes.fromhex("0103020001")
            assert s.recv(100) == body + crc16(body)
        res = expect_ok(mb(server.socket_target, "read-holding-registers", "2", "--framer", "rtu"))
        assert plain_pairs(res) == [(2, "2")]


def test_rtu_frames_are_ended_by_silence_when_their_length_misleads():
    """A reply from another slave on the bus is no CRC error, and a longer FC08 query is echoed."""
    with serve("--framer", "rtu") as server:
        with _raw(server) as s:
            other = bytes.fromhex("020304000100 02".replace(" ", ""))  # unit 2 answering FC03
            s.sendall(other + crc16(other))
            time.sleep(0.2)
            query = bytes.fromhex("01080000A5370102")  # return query data, 4 bytes
            s.sendall(query + crc16(query))
            assert s.recv(100) == query + crc16(query)
            errors = bytes.fromhex("0108000C0000")
            s.sendall(errors + crc16(errors))
            assert s.recv(100) == bytes.fromhex("0108000C0000") + crc16(bytes.fromhex("0108000C0000"))
