"""Dumping a device end to end (issue 16): mbtool dump of pymodbus's device with holes and of
crafted identities, serve --data of the dump answering as the device did, a dump interrupted,
diff and restore against a device, and --changes while the device's values change."""

from __future__ import annotations

import contextlib
import json

import pytest
from helpers.checks import expect_ok, parse_hex_lines
from helpers.frames import mbap, read_mbap
from helpers.run import interrupt_after, run_cli, start_mbtool
from helpers.served import pymodbus_tcp, serve

# --- mbtool dump end to end: pymodbus's device with holes, and serve --data of its dump ----------

SECTIONS = {
    "coils": "coils",
    "discrete": "discrete_inputs",
    "holding": "holding_registers",
    "input": "input_registers",
}
RANGES = (
    "--range",
    "coils:0-99",
    "--range",
    "discrete:0-99",
    "--range",
    "holding:0-599",
    "--range",
    "input:0-599",
)


def _expanded(section: dict) -> dict[int, int]:
    values = {}
    for key, value in section.items():
        items = [value["value"]] * value["count"] if isinstance(value, dict) else value
        values.update({int(key) + i: int(v) for i, v in enumerate(items)})
    return values


def test_a_dump_of_a_device_with_holes_finds_them_exactly(holed_device, tmp_path):
    import tomllib

    from pymodbus.client import ModbusTcpClient

    path = tmp_path / "device.toml"
    res = expect_ok(run_cli("dump", path, *RANGES, "-p", holed_device.target))
    assert res.stdout == "" and len(res.stderr.splitlines()) == 1  # in a pipe: the summary only
    data = tomllib.loads(path.read_text())
    assert data["sparse"] is True and "complete" not in data
    # What pymodbus's own client finds, one address at a time, is what the dump holds.
    client = ModbusTcpClient(holed_device.host, port=holed_device.port, timeout=2, retries=0)
    assert client.connect()
    try:
        for table, method, size in (
            ("holding", "read_holding_registers", 600),
            ("input", "read_input_registers", 600),
            ("coils", "read_coils", 100),
            ("discrete", "read_discrete_inputs", 100),
        ):
            expected = {}
            for address in range(size):
                reply = getattr(client, method)(address, count=1, device_id=1)
                if not reply.isError():
                    expected[address] = int(reply.registers[0] if "registers" in method else reply.bits[0])
            assert _expanded(data[SECTIONS[table]]) == expected, table
            assert f"{table} {len(expected)}" in res.stderr
    finally:
        client.close()
    assert list(_expanded(data["holding_registers"])) == [*range(10), *range(20, 30), 500, 502, 503]
    assert data["input_registers"]["300"] == {"value": 4, "count": 40}  # a long run stays compact
    assert data["identity"]["objects"]["0"] == "Pymodbus"


def test_serve_of_a_dump_answers_as_the_device_did(holed_device, tmp_path):
    from pymodbus.client import ModbusTcpClient

    path = tmp_path / "device.toml"
    expect_ok(run_cli("dump", path, *RANGES, "-p", holed_device.target))
    original = ModbusTcpClient(holed_device.host, port=holed_device.port, timeout=2, retries=0)
    assert original.connect()
    with serve("--data", str(path)) as server:
        copy = ModbusTcpClient(server.host, port=server.port, timeout=2, retries=0)
        assert copy.connect()
        try:
            reads = [
                ("read_holding_registers", 600),
                ("read_input_registers", 600),
                ("read_coils", 100),
                ("read_discrete_inputs", 100),
            ]
            for method, size in reads:
                for address in range(size):
                    for count in (1, 3):
                        a = getattr(original, method)(address, count=count, device_id=1)
                        b = getattr(copy, method)(address, count=count, device_id=1)
                        assert a.isError() == b.isError(), (method, address, count)
                        if a.isError():
                            assert a.exception_code == b.exception_code == 2
                        else:
                            assert a.registers == b.registers and a.bits[:count] == b.bits[:count]
            assert original.read_device_information(device_id=1).information[0] == b"Pymodbus"
            assert copy.read_device_information(device_id=1).information[0] == b"Pymodbus"
        finally:
            copy.close()
            original.close()


# A device whose identity differs from the simulator's defaults in every way a dump must keep:
# FC 17 with run indicator OFF and bytes that are no text, FC 43/14 with only the basic
# objects (no 03..06) and conformity 81 (basic, stream and individual access).
CRAFTED_SLAVE_ID = bytes([0x11, 0x08, 0x2A, 0x00]) + b"\x01\x02v1.0"
CRAFTED_OBJECTS = {0x00: b"ACME", 0x01: b"PLC-7", 0x02: b"2.1"}


def _crafted_identity(request: bytes) -> bytes:
    """MBAP replies of the crafted device: its identity, and exception 02 to every read."""
    import struct

    tid, _, _, unit = struct.unpack(">HHHB", request[:7])
    pdu = request[7:]
    if pdu[:1] == b"\x11":
        reply = CRAFTED_SLAVE_ID
    elif pdu[:2] == b"\x2b\x0e" and pdu[2] == 4:
        value = CRAFTED_OBJECTS.get(pdu[3])
        reply = (
            b"\xab\x02"
            if value is None
            else bytes([0x2B, 0x0E, 4, 0x81, 0, 0, 1, pdu[3], len(value)]) + value
        )
    elif pdu[:2] == b"\x2b\x0e":
        objects = b"".join(bytes([i, len(v)]) + v for i, v in CRAFTED_OBJECTS.items())
        reply = bytes([0x2B, 0x0E, pdu[2], 0x81, 0, 0, len(CRAFTED_OBJECTS)]) + objects
    else:
        reply = bytes([pdu[0] | 0x80, 0x02])
    return struct.pack(">HHHB", tid, 0, len(reply) + 1, unit) + reply


def _identity_replies(host: str, port: int, asked: list[bytes] | None = None) -> tuple[list, list]:
    """(requests, replies): FC 17, FC 43/14 read codes 1-3 from object 0 following
    more-follows, and read code 4 for each object there is and one there is not; the whole
    MBAP replies.  ``asked``: send these requests instead (the other side's)."""
    import socket

    requests = list(asked) if asked is not None else [b"\x11"]
    replies = []
    with socket.create_connection((host, port), timeout=5) as sock:

        def ask(pdu: bytes) -> bytes:
            sock.sendall(mbap(len(replies) + 1, 1, pdu))
            tid, unit, reply = read_mbap(sock)
            replies.append((tid, unit, reply))
            return reply

        if asked is not None:
            for pdu in requests:
                ask(pdu)
            return requests, replies
        ask(b"\x11")
        for code in (1, 2, 3):
            next_id = 0
            while True:
                requests.append(bytes([0x2B, 0x0E, code, next_id]))
                reply = ask(requests[-1])
                if reply[0] != 0x2B or reply[4] != 0xFF:
                    break
                next_id = reply[5]
        for object_id in [*range(7), *range(0x80, 0x85), 0x10]:
            requests.append(bytes([0x2B, 0x0E, 4, object_id]))
            ask(requests[-1])
    return requests, replies


@pytest.mark.parametrize("original", ["pymodbus", "crafted", "without"])
def test_serve_of_a_dump_answers_fc17_and_fc43_byte_for_byte(original, holed_device, raw_responder, tmp_path):
    """pymodbus's device, a crafted one, and one without FC 17 and FC 43 (exception 01 to both,
    as many Modbus TCP devices answer FC 17): the copy answers as the device did."""
    import tomllib

    with contextlib.ExitStack() as stack:
        if original == "pymodbus":  # its FC 17 sends text first: run indicator byte 79 ('y')
            host, port = holed_device.host, holed_device.port
        elif original == "crafted":
            host, port = "127.0.0.1", raw_responder(_crafted_identity).port
        else:
            device = stack.enter_context(serve("--exception", "17:1", "--exception", "43:1"))
            host, port = device.host, device.port
        path = tmp_path / "device.toml"
        expect_ok(run_cli("dump", path, "--range", "holding:0-9", "-p", f"tcp://{host}:{port}"))
        identity = tomllib.loads(path.read_text())["identity"]
        assert ("refused" in identity) == (original == "without")
        requests, expected = _identity_replies(host, port)
    with serve("--data", str(path)) as server:
        _, replies = _identity_replies(server.host, server.port, requests)
    for request, want, got in zip(requests, expected, replies, strict=True):
        assert got == want, f"request {request.hex(' ')}: {got[2].hex(' ')} != {want[2].hex(' ')}"


def test_a_device_that_refuses_the_extended_stream_still_gets_its_objects_dumped(raw_responder, tmp_path):
    import struct
    import tomllib

    def basic_only(request: bytes) -> bytes:
        pdu = request[7:]
        if pdu[:2] == b"\x2b\x0e" and pdu[2] in (2, 3):  # exception 03: no such read code here
            tid, _, _, unit = struct.unpack(">HHHB", request[:7])
            return struct.pack(">HHHB", tid, 0, 3, unit) + b"\xab\x03"
        return _crafted_identity(request)

    device = raw_responder(basic_only)
    path = tmp_path / "device.toml"
    expect_ok(run_cli("dump", path, "--range", "holding:0-9", "-p", f"tcp://127.0.0.1:{device.port}"))
    identity = tomllib.loads(path.read_text())["identity"]
    assert identity["objects"] == {"0": "ACME", "1": "PLC-7", "2": "2.1"} and identity["conformity"] == 0x81
    assert identity["run"] is False and identity["extra"] == [1, 2, *b"v1.0"]


def test_a_dump_cut_short_is_a_valid_file_marked_incomplete(holed_device, tmp_path):
    import tomllib

    path = tmp_path / "part.toml"
    res = run_cli("dump", path, *RANGES, "--max-requests", "5", "-p", holed_device.target)
    # Not 0: a dump that did not finish must not look like one that did (issue 28).
    assert res.returncode == 8 and "stopped after 5 requests (--max-requests)" in res.stderr
    data = tomllib.loads(path.read_text())
    assert data["complete"] is False and data["sparse"] is True
    res = run_cli("dump", "-", "--range", "holding:5-2", "-p", holed_device.target)
    assert res.returncode == 2 and "FIRST no more than LAST" in res.stderr


def test_ctrl_c_keeps_what_was_read_in_a_valid_file(tmp_path):
    import signal
    import tomllib

    path = tmp_path / "part.toml"
    with serve("--delay", "0.02") as server:
        target = f"tcp://{server.host}:{server.port}"
        code, _, err = interrupt_after(["dump", str(path), "-p", target], 0, signal.SIGINT)
    assert code == 130, err
    assert "interrupted: the file has what was read, marked complete = false" in err
    data = tomllib.loads(path.read_text())
    assert data["complete"] is False and data["coils"]  # the coils came first, and stay


def _requests_served(server, count: int, wait: float = 30.0) -> None:
    """Return once ``serve`` (log mode) has logged ``count`` requests."""
    import time

    end = time.monotonic() + wait
    while (seen := server.log().count(" RX ")) < count:
        assert time.monotonic() < end, f"serve logged {seen} requests in {wait} s"
        time.sleep(0.02)


def _dump_process(args):

    return start_mbtool("dump", *args)


@pytest.mark.parametrize(
    "first, second", [("SIGINT", "SIGINT"), ("SIGINT", "SIGTERM"), ("SIGTERM", "SIGTERM")]
)
def test_a_second_interrupt_still_saves_what_was_read(tmp_path, first, second):
    import signal
    import time
    import tomllib

    path = tmp_path / "part.toml"
    with serve("--delay", "0.01", quiet=False) as server:
        proc = _dump_process([str(path), "-p", f"tcp://{server.host}:{server.port}"])
        _requests_served(server, 10)
        proc.send_signal(getattr(signal, first))
        # The second signal comes again and again until the file is there: none may lose it.
        end = time.monotonic() + 5
        while proc.poll() is None and not path.exists() and time.monotonic() < end:
            proc.send_signal(getattr(signal, second))
            time.sleep(0.002)
        _, err = proc.communicate(timeout=30)
    assert proc.returncode == 130, err
    assert "interrupted: the file has what was read, marked complete = false" in err
    data = tomllib.loads(path.read_text())
    assert data["complete"] is False and data["coils"]
    assert [p.name for p in tmp_path.iterdir()] == ["part.toml"]  # no temporary file left


def test_a_hang_up_saves_what_was_read_and_leaves_no_temporary_file(tmp_path):
    """SIGHUP (the terminal or ssh session gone, issue 40's signals campaign): the dump died
    as a program that does not catch it, leaving its `.part` file and no dump. A hang-up
    interrupts it as Ctrl-C does."""
    import signal
    import tomllib

    path = tmp_path / "part.toml"
    with serve("--delay", "0.01", quiet=False) as server:
        proc = _dump_process([str(path), "-p", f"tcp://{server.host}:{server.port}"])
        _requests_served(server, 10)
        proc.send_signal(signal.SIGHUP)
        _, err = proc.communicate(timeout=30)
    assert proc.returncode == 130, err
    assert "interrupted: the file has what was read, marked complete = false" in err
    assert tomllib.loads(path.read_text())["complete"] is False
    assert [p.name for p in tmp_path.iterdir()] == ["part.toml"]


# --- mbtool diff ----------------------------------------------------------------------------


def test_diff_of_a_device_against_its_own_dump_then_after_one_write(tcp_device, tmp_path):
    from pymodbus.client import ModbusTcpClient

    path = tmp_path / "before.toml"
    ranges = ("--range", "holding:700-720", "--range", "coils:700-710")
    expect_ok(run_cli("dump", path, *ranges, "-p", tcp_device.target))
    res = run_cli("diff", path, "-p", tcp_device.target)
    assert res.returncode == 0 and res.stdout == "" and res.stderr == ""
    client = ModbusTcpClient(tcp_device.host, port=tcp_device.port, timeout=2, retries=0)
    assert client.connect()
    try:
        client.write_register(705, 99, device_id=1)
        res = run_cli("diff", path, "-p", tcp_device.target)
        assert res.returncode == 1 and res.stdout.splitlines() == ["holding 705: 0 -> 99"]
        assert res.stderr == "mbtool: 1 difference\n"
        res = run_cli("diff", "device", path, "-p", tcp_device.target)  # either side may be the device
        assert res.returncode == 1 and res.stdout.splitlines() == ["holding 705: 99 -> 0"]
        mapped = tmp_path / "map.toml"
        mapped.write_text('[points.setpoint]\nref = 40706\nscale = 0.5\nunit = "bar"\n')
        res = run_cli("diff", path, "-m", mapped, "-p", tcp_device.target, "-o", "json")
        data = json.loads(res.stdout)
        assert res.returncode == 1 and data["equal"] is False
        assert data["differences"] == [
            {
                "table": "holding",
                "address": 705,
                "ref": "40706",
                "name": "setpoint",
                "unit": "bar",
                "a": 0,
                "b": 49.5,
            }
        ]
        # A point without an engineering unit has no "unit" (read -m's rule).
        mapped.write_text("[points.setpoint]\nref = 40706\n")
        res = run_cli("diff", path, "-m", mapped, "-p", tcp_device.target, "-o", "json")
        assert res.returncode == 1 and "unit" not in json.loads(res.stdout)["differences"][0]
    finally:
        client.write_register(705, 0, device_id=1)
        client.close()


# --- mbtool restore -------------------------------------------------------------------------


def test_restore_writes_back_only_what_differs_and_confirms(tcp_device, tmp_path):
    from pymodbus.client import ModbusTcpClient

    path = tmp_path / "saved.toml"
    ranges = ("--range", "holding:740-760", "--range", "coils:740-750", "--range", "input:0-3")
    expect_ok(run_cli("dump", path, *ranges, "-p", tcp_device.target))
    client = ModbusTcpClient(tcp_device.host, port=tcp_device.port, timeout=2, retries=0)
    assert client.connect()
    try:
        client.write_registers(744, [11, 12], device_id=1)
        client.write_register(750, 13, device_id=1)
        client.write_coil(745, True, device_id=1)
        res = expect_ok(run_cli("restore", path, "--dry-run", "-o", "plain", "-p", tcp_device.target))
        # Only what differs, as diff lists it: the coil, then 744-745 and 750 (3 requests).
        assert res.stdout.splitlines() == [
            "coils 745: 1 -> 0",
            "holding 744: 11 -> 0",
            "holding 745: 12 -> 0",
            "holding 750: 13 -> 0",
        ]
        assert "nothing was sent: 3 requests would write 4 values" in res.stderr
        assert client.read_holding_registers(744, count=2, device_id=1).registers == [11, 12]
        res = expect_ok(run_cli("restore", path, "--hex", "-p", tcp_device.target))
        writes = [line.data[7] for line in parse_hex_lines(res.stderr) if line.direction == "TX"]
        assert writes.count(0x10) == 2 and writes.count(0x0F) == 1 and 0x06 not in writes
        assert "restore: wrote 1 coil, 3 holding registers in 3 requests" in res.stderr
        assert "skipped 4 input registers (read-only)" in res.stderr
        assert "read back and confirmed" in res.stderr
        assert res.stdout.splitlines()[0] == "confirmed coils 745: 1 -> 0"  # each write, and its fate
        assert client.read_holding_registers(744, count=7, device_id=1).registers == [0] * 7
        assert client.read_coils(745, count=1, device_id=1).bits[0] is False
        assert run_cli("diff", path, "-p", tcp_device.target).returncode == 0
    finally:
        client.close()


# --- --changes on polling -------------------------------------------------------------------


def _poll_while_writing(args, writes):
    """Run a polling mbtool; while it polls, make the writes through pymodbus's client."""
    import select
    import time

    with serve() as server:
        target = f"tcp://{server.host}:{server.port}"
        proc = start_mbtool(*args, "-p", target)
        # Wait for the first poll's output without reading it (communicate reads it all).
        assert select.select([proc.stdout.fileno()], [], [], 15)[0], "no first poll"
        client = pymodbus_tcp(server)
        try:
            for address, value in writes:
                client.write_register(address, value, device_id=1)
                time.sleep(0.4)
        finally:
            client.close()
        out, err = proc.communicate(timeout=20)
    return proc.returncode, out, err


def test_changes_prints_the_first_poll_then_one_line_a_change():
    code, out, err = _poll_while_writing(
        ["read-holding-registers", "0", "3", "--interval", "0.1", "--polls", "25", "--changes"],
        [(1, 77), (2, 5)],
    )
    assert code == 0, err
    lines = [line.split(" ", 1)[1] for line in out.splitlines()]
    assert lines == ["0 0", "1 1", "2 2", "holding 1: 1 -> 77", "holding 2: 2 -> 5"]


def test_changes_of_a_map_and_as_json(pump_map):
    code, out, err = _poll_while_writing(
        ["read", "-m", pump_map, "--interval", "0.1", "--polls", "20", "--changes", "-o", "json"],
        [(500, 225)],
    )
    assert code == 0, err
    first, *changes = (json.loads(line) for line in out.splitlines())
    assert [p["name"] for p in first["points"]] == ["setpoint"]
    assert [{k: v for k, v in c.items() if k != "time"} for c in changes] == [
        {"name": "setpoint", "ref": "40501", "old": 0, "new": 22.5, "unit": "m3/h"}
    ]


def test_changes_as_csv_are_rows_under_the_first_polls_header(pump_map):
    """-o csv writes one header: a change is a row of the same columns, the value it changed to."""
    import csv

    code, out, err = _poll_while_writing(
        ["read-holding-registers", "0", "3", "--interval", "0.1", "--polls", "25", "--changes", "-o", "csv"],
        [(1, 77)],
    )
    assert code == 0, err
    rows = list(csv.reader(out.splitlines()))
    assert rows[0] == ["time", "address", "value"]
    assert all(len(row) == 3 for row in rows), out
    assert [row[1:] for row in rows[1:]] == [["0", "0"], ["1", "1"], ["2", "2"], ["1", "77"]]
    code, out, err = _poll_while_writing(
        ["read", "-m", pump_map, "--interval", "0.1", "--polls", "20", "--changes", "-o", "csv"],
        [(500, 225)],
    )
    assert code == 0, err
    header, *rows = csv.reader(out.splitlines())
    assert header == ["time", "name", "value", "unit", "ref", "registers"]
    assert [row[1:] for row in rows] == [
        ["setpoint", "0", "m3/h", "40501", "0"],
        ["setpoint", "22.5", "m3/h", "40501", "225"],
    ]


def test_changes_of_a_read_by_reference_name_the_reference():
    """read 40002 shows its first poll by reference: its changes say the same reference."""
    code, out, err = _poll_while_writing(
        ["read", "40002", "2", "--interval", "0.1", "--polls", "25", "--changes"], [(1, 77)]
    )
    assert code == 0, err
    lines = [line.split(" ", 1)[1] for line in out.splitlines()]
    assert lines == ["40002 1", "40003 2", "40002: 1 -> 77"]
    code, out, err = _poll_while_writing(
        ["read", "40002", "2", "--interval", "0.1", "--polls", "25", "--changes", "-o", "json"], [(1, 77)]
    )
    assert code == 0, err
    first, change = (json.loads(line) for line in out.splitlines())
    assert first["refs"] == ["40002", "40003"]
    assert {k: v for k, v in change.items() if k != "time"} == {
        "unit": 1,
        "table": "holding",
        "address": 1,
        "ref": "40002",
        "old": 1,
        "new": 77,
    }


@pytest.fixture
def pump_map(tmp_path):
    path = tmp_path / "pump.toml"
    path.write_text('[points.setpoint]\nref = 40501\nscale = 0.1\nunit = "m3/h"\n')
    return path
