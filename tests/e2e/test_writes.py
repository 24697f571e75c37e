"""Writes of several requests, end to end (issues 28 §2, 29 items 7, 10 and 15): write -m
and restore say exactly what changed when a write fails part-way (refused, unanswered,
or the connection closed), a map keeps a point's registers in one request, and every
value is checked against its point's type before anything is sent.

Peers: pymodbus's device with holes in its address map, mbtool serve with a sparse data
file or --read-only, and a raw responder written here that stops answering, or hangs up,
after a number of writes.
"""

from __future__ import annotations

import json
import struct

import pytest
from helpers.checks import assert_one_error_line, expect_ok, parse_hex_lines
from helpers.devices import start_device
from helpers.run import run_cli, start_mbtool
from helpers.served import pymodbus_tcp, serve
from helpers.sockets import CLOSE

pytestmark = pytest.mark.timeout(90)

FAST = ("--timeout", "0.5", "--retries", "0")


def stderr_lines(res) -> list[str]:
    return [line for line in res.stderr.splitlines() if line.strip()]


def one_summary(res, code: int) -> str:
    """The run's one stderr line (exit ``code``, no traceback)."""
    assert res.returncode == code, str(res)
    assert "Traceback" not in res.stderr, str(res)
    (line,) = stderr_lines(res)
    assert line.startswith("mbtool: "), str(res)
    return line


class TcpPlant:
    """A Modbus TCP device in a few lines, for a raw responder: FC 01/03 read and FC 06/15/16
    write its coils and holding registers (0 where never written).  After ``answered``
    writes it stops answering (``then`` None) or hangs up (``then`` CLOSE)."""

    def __init__(self, answered: int, then) -> None:
        self.answered, self.then = answered, then
        self.holding: dict[int, int] = {}
        self.coils: dict[int, int] = {}
        self.writes = 0

    def __call__(self, request: bytes):
        tid, _, _, unit, function = struct.unpack(">HHHBB", request[:8])
        address, count = struct.unpack(">HH", request[8:12])
        if function == 3:
            data = b"".join(
                struct.pack(">H", self.holding.get(a, 0)) for a in range(address, address + count)
            )
            pdu = bytes([3, len(data)]) + data
        elif function == 1:
            bits = [self.coils.get(a, 0) for a in range(address, address + count)]
            data = bytes(sum(b << i for i, b in enumerate(bits[k : k + 8])) for k in range(0, count, 8))
            pdu = bytes([1, len(data)]) + data
        elif function in (6, 15, 16):
            if self.writes >= self.answered:
                return self.then
            self.writes += 1
            if function == 6:  # the "count" is the value
                self.holding[address] = count
                return request
            values = request[13:]
            for i in range(count):
                if function == 16:
                    self.holding[address + i] = struct.unpack(">H", values[2 * i : 2 * i + 2])[0]
                else:
                    self.coils[address + i] = values[i // 8] >> (i % 8) & 1
            pdu = bytes([function]) + struct.pack(">HH", address, count)
        else:
            pdu = bytes([function | 0x80, 1])
        return struct.pack(">HHHB", tid, 0, len(pdu) + 1, unit) + pdu


# --- a write that fails part-way says what it already wrote (issue 28 §2, issue 29 item 15) ----

THREE = """\
[points.a]
ref = 40501
access = "rw"

[points.b]
ref = 40502
access = "rw"

[points.c]
ref = 40503
access = "rw"
"""


@pytest.fixture
def three(tmp_path):
    path = tmp_path / "three.toml"
    path.write_text(THREE)
    return path


def test_a_map_write_refused_part_way_lists_what_was_written(three):
    # pymodbus's device with holes: 40501 and 40503 exist, 40502 does not (exception 02).
    with start_device(tcp=True, framer="socket", units="1", holes=True) as device:
        from pymodbus.client import ModbusTcpClient

        res = run_cli("write", "-m", three, "a=1", "b=2", "c=3", "-p", device.target)
        line = one_summary(res, 4)  # the failure's own code: an exception reply
        assert "write stopped at b (40502): exception 02 Illegal Data Address" in line
        assert line.endswith("; 1 written, 1 refused, 1 not sent")
        assert res.stdout.splitlines() == [
            "written a (40501): 1",
            "refused b (40502): 2",
            "not-sent c (40503): 3",
        ]
        client = ModbusTcpClient(device.host, port=device.port, timeout=2, retries=0)
        assert client.connect()
        try:
            assert client.read_holding_registers(500, count=1, device_id=1).registers == [1]
            assert client.read_holding_registers(502, count=1, device_id=1).registers == [8]  # not sent
        finally:
            client.close()


def test_a_map_write_to_a_read_only_device_as_json(three):
    with serve("--read-only") as server:
        target = f"tcp://{server.host}:{server.port}"
        res = run_cli("write", "-m", three, "a=1", "b=2", "-o", "json", "-p", target)
        one_summary(res, 4)
        data = json.loads(res.stdout)  # one object: the report carries the error itself
        assert data["exit_code"] == 4 and "exception 01 Illegal Function" in data["error"]
        assert data["map"] == str(three) and data["unit"] == 1  # the unit id; a point without
        assert data["writes"] == [  # an engineering unit has no "unit" (read -m's rule)
            {
                "table": "holding",
                "address": 500,
                "ref": "40501",
                "name": "a",
                "new": 1,
                "status": "refused",
            },
            {
                "table": "holding",
                "address": 501,
                "ref": "40502",
                "name": "b",
                "new": 2,
                "status": "not-sent",
            },
        ]


SAVED = """\
sparse = true
[coils]
0 = [1]
[holding_registers]
0 = [5, 6]
10 = [7]
20 = [8]
"""
SPARSE_DEVICE = """\
sparse = true
[coils]
0 = [0]
[holding_registers]
0 = [0, 0]
20 = [0]
"""


def test_a_restore_refused_part_way_lists_each_write_and_its_fate(tmp_path):
    saved, data = tmp_path / "saved.toml", tmp_path / "device.toml"
    saved.write_text(SAVED)
    data.write_text(SPARSE_DEVICE)  # no holding register 10: a write there is exception 02
    with serve("--data", str(data)) as server:
        target = f"tcp://{server.host}:{server.port}"
        res = run_cli("restore", saved, "-p", target)
        line = one_summary(res, 4)
        assert "restore stopped at holding 10: exception 02 Illegal Data Address" in line
        assert line.endswith("; 3 written (read back and confirmed), 1 refused, 1 not sent")
        assert res.stdout.splitlines() == [
            "confirmed coils 0: 0 -> 1",
            "confirmed holding 0: 0 -> 5",
            "confirmed holding 1: 0 -> 6",
            "refused holding 10: missing -> 7",
            "not-sent holding 20: 0 -> 8",
        ]
        client = pymodbus_tcp(server)
        try:
            assert client.read_coils(0, count=1, device_id=1).bits[0] is True
            assert client.read_holding_registers(0, count=2, device_id=1).registers == [5, 6]
            assert client.read_holding_registers(20, count=1, device_id=1).registers == [0]  # not sent
            client.write_coil(0, False, device_id=1)
            client.write_registers(0, [0, 0], device_id=1)
        finally:
            client.close()
        res = run_cli("restore", saved, "-o", "json", "-p", target)
        one_summary(res, 4)
        report = json.loads(res.stdout)
        assert report["exit_code"] == 4 and report["file"] == str(saved)
        assert [(w["table"], w["address"], w["old"], w["new"], w["status"]) for w in report["writes"]] == [
            ("coils", 0, 0, 1, "confirmed"),
            ("holding", 0, 0, 5, "confirmed"),
            ("holding", 1, 0, 6, "confirmed"),
            ("holding", 10, None, 7, "refused"),
            ("holding", 20, 0, 8, "not-sent"),
        ]


RUNS = "sparse = true\n[holding_registers]\n0 = [1]\n10 = [2]\n20 = [3]\n30 = [4]\n"


@pytest.mark.parametrize("then, words", [(None, "no response from unit 1"), (CLOSE, "closed the connection")])
def test_a_device_that_stops_answering_or_hangs_up_mid_restore(raw_responder, tmp_path, then, words):
    saved = tmp_path / "saved.toml"
    saved.write_text(RUNS)  # four runs: four requests
    plant = TcpPlant(answered=2, then=then)
    server = raw_responder(plant)
    res = run_cli("restore", saved, *FAST, "-p", server.tcp_target)
    line = one_summary(res, 3)  # no response, or the connection closed: exit 3 either way
    assert "restore stopped at holding 20: " in line and words in line
    # The device answered before: this is no framing mix-up, and no gateway is suggested.
    assert "RTU" not in line and "gateway" not in line
    assert line.endswith(
        "; 2 written (not read back), 1 failed (no valid reply: it may or may not have been written), 1 not sent"
    )
    assert res.stdout.splitlines() == [
        "written holding 0: 0 -> 1",
        "written holding 10: 0 -> 2",
        "failed holding 20: 0 -> 3",
        "not-sent holding 30: 0 -> 4",
    ]
    assert plant.holding == {0: 1, 10: 2}


def test_ctrl_c_mid_restore_lists_what_was_written(raw_responder, tmp_path):
    import signal
    import time

    saved = tmp_path / "saved.toml"
    saved.write_text(RUNS)
    plant = TcpPlant(answered=2, then=None)  # the third write waits for a reply that never comes
    server = raw_responder(plant)
    proc = start_mbtool("restore", saved, "--timeout", "30", "-p", server.tcp_target)
    deadline = time.monotonic() + 20  # until the third write is out, waiting for its reply
    while sum(request[7] == 0x10 for request in server.requests) < 3 and time.monotonic() < deadline:
        time.sleep(0.05)
    time.sleep(0.3)
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=15)
    assert proc.returncode == 130, err
    assert "Traceback" not in err
    assert err.splitlines() == [
        "mbtool: restore stopped at holding 20: interrupted; 2 written (not read back), 1 failed "
        "(no valid reply: it may or may not have been written), 1 not sent"
    ]
    assert out.splitlines() == [
        "written holding 0: 0 -> 1",
        "written holding 10: 0 -> 2",
        "failed holding 20: 0 -> 3",
        "not-sent holding 30: 0 -> 4",
    ]


def test_a_map_write_to_a_device_that_hangs_up(raw_responder, three):
    server = raw_responder(TcpPlant(answered=1, then=CLOSE))
    res = run_cli("write", "-m", three, "a=1", "b=2", "c=3", *FAST, "-p", server.tcp_target)
    line = one_summary(res, 3)
    assert "write stopped at b (40502)" in line and "closed the connection" in line
    assert res.stdout.splitlines() == [
        "written a (40501): 1",
        "failed b (40502): 2",
        "not-sent c (40503): 3",
    ]


# --- restore -m: a point's registers together; a dry run lists what would change ----------------

METER = """\
[points.level]
ref = 40101
type = "float32"
unit = "m"
access = "rw"

[points.alarm]
ref = 40111
bit = 3
"""


def test_restore_with_a_map_writes_a_point_whole_and_its_dry_run_reads_like_diff(tmp_path):
    meter, saved, data = tmp_path / "meter.toml", tmp_path / "saved.toml", tmp_path / "device.toml"
    meter.write_text(METER)
    # The dump's level is 1.5 (3FC0 0000); the device's 2.5 (4020 0000) differs in one word.
    saved.write_text("sparse = true\n[holding_registers]\n100 = [0x3FC0, 0, 0, 0, 0]\n110 = [8]\n")
    data.write_text("sparse = true\n[holding_registers]\n100 = [0x4020, 0, 0, 0, 0]\n110 = [0]\n")
    with serve("--data", str(data)) as server:
        target = f"tcp://{server.host}:{server.port}"
        res = expect_ok(run_cli("restore", saved, "--dry-run", "-m", meter, "-p", target))
        assert res.stdout.splitlines() == ["level (40101): 2.5 m -> 1.5 m", "alarm (40111): off -> on"]
        assert res.stdout == run_cli("diff", "device", saved, "-m", meter, "-p", target).stdout
        assert "raw " not in res.stdout  # no decoded frames
        assert "dry run: the device was read; nothing was sent: 2 requests would write 2 values" in res.stderr
        res = expect_ok(run_cli("restore", saved, "--dry-run", "-p", target, "-o", "json"))
        assert json.loads(res.stdout)["writes"] == [
            {"table": "holding", "address": 100, "ref": "40101", "old": 0x4020, "new": 0x3FC0},
            {"table": "holding", "address": 110, "ref": "40111", "old": 0, "new": 8},
        ]
        # Without a map only the word that differs is written; with one, the whole float32.
        res = expect_ok(run_cli("restore", saved, "-m", meter, "--hex", "-p", target))
        writes = [line.data[7:12] for line in parse_hex_lines(res.stderr) if line.direction == "TX"]
        writes = [pdu for pdu in writes if pdu[0] == 0x10]
        assert writes == [bytes([0x10, 0, 100, 0, 2]), bytes([0x10, 0, 110, 0, 1])]
        assert res.stdout.splitlines() == [
            "confirmed level (40101): 2.5 m -> 1.5 m",
            "confirmed alarm (40111): off -> on",
        ]
        client = pymodbus_tcp(server)
        try:
            assert client.read_holding_registers(100, count=2, device_id=1).registers == [0x3FC0, 0]
        finally:
            client.close()


def test_write_requests_never_cut_a_point_in_two():
    from mbtool.cli.commands.snapshot import write_requests

    changes = {"holding": {a: 0 for a in range(200)}}
    requests = write_requests(changes, [("holding", 122, 124)])  # a float32 across the 123 limit
    assert [(r.address, len(r.values)) for r in requests] == [(0, 122), (122, 78)]
    assert [(r.address, len(r.values)) for r in write_requests(changes)] == [(0, 123), (123, 77)]


# --- what restore and diff read: complete = false, [units.N] (issue 29 item 10) -------------------


def test_restore_of_an_incomplete_dump_warns(tmp_path):
    saved = tmp_path / "part.toml"
    saved.write_text("sparse = true\ncomplete = false\n[holding_registers]\n300 = [1]\n")
    res = expect_ok(run_cli("restore", saved, "-p", "sim://"))
    assert (
        f"mbtool: warning: {saved} is marked complete = false: the dump stopped early, and only "
        "what it holds is restored" in stderr_lines(res)
    )
    assert res.stdout.splitlines() == ["confirmed holding 300: 0 -> 1"]


@pytest.mark.parametrize("command", ["diff", "restore"])
def test_diff_and_restore_refuse_per_unit_sections(silent_server, tmp_path, command):
    saved = tmp_path / "serve.toml"
    saved.write_text("[holding_registers]\n0 = [1]\n[units.2.holding_registers]\n0 = [2]\n")
    res = run_cli(command, saved, *FAST, "-p", silent_server.tcp_target)
    line = assert_one_error_line(res, 2)
    assert f"{saved} has [units.2]" in line
    assert silent_server.received_bytes() == b""


def test_diff_with_a_map_shows_bits_as_on_and_off(tmp_path):
    meter = tmp_path / "meter.toml"
    meter.write_text(METER + '\n[points.relay]\nref = "00001"\n')
    (tmp_path / "a.toml").write_text("sparse = true\n[holding_registers]\n110 = [0]\n[coils]\n0 = 1\n")
    (tmp_path / "b.toml").write_text("sparse = true\n[holding_registers]\n110 = [8]\n[coils]\n0 = 0\n")
    res = run_cli("diff", tmp_path / "a.toml", tmp_path / "b.toml", "-m", meter)
    assert res.returncode == 1
    assert res.stdout.splitlines() == ["alarm (40111): off -> on", "relay (00001): on -> off"]


def test_diff_with_a_map_says_a_value_an_enum_does_not_label(tmp_path):
    """As read -m shows it (issue 28 §5): 'mode (40121): auto -> 7 (no label)'; JSON keeps the number."""
    meter = tmp_path / "meter.toml"
    meter.write_text('[points.mode]\nref = 40121\nenum = { 1 = "auto", 2 = "manual" }\n')
    (tmp_path / "a.toml").write_text("sparse = true\n[holding_registers]\n120 = [1]\n")
    (tmp_path / "b.toml").write_text("sparse = true\n[holding_registers]\n120 = [7]\n")
    res = run_cli("diff", tmp_path / "a.toml", tmp_path / "b.toml", "-m", meter)
    assert res.returncode == 1 and res.stdout.splitlines() == ["mode (40121): auto -> 7 (no label)"]
    res = run_cli("diff", tmp_path / "a.toml", tmp_path / "b.toml", "-m", meter, "-o", "json")
    (difference,) = json.loads(res.stdout)["differences"]
    assert (difference["a"], difference["b"]) == ("auto", 7)


# --- every value checked against its point before anything is sent (issue 28 §2, 29 item 7) -------

VALUES = """\
[points.level]
ref = 40101
type = "float32"
unit = "m"
access = "rw"

[points.total]
ref = 40103
type = "float64"
access = "rw"

[points.d]
ref = 40107
type = "float32"
scale = 1e-300
access = "rw"

[points.demand_period]
ref = 40111
unit = "min"
access = "rw"

[points.word]
ref = 40112
type = "hex"
access = "rw"
"""


@pytest.fixture
def values_map(tmp_path):
    path = tmp_path / "values.toml"
    path.write_text(VALUES)
    return path


@pytest.mark.parametrize(
    "assignments, words",
    [
        (["total=1e400"], "total: 1e400 is out of float64's range"),  # was +inf, exit 0
        (["d=1e10"], "d: 1e10 (raw 1E+310) is out of float32's range"),  # was +inf, then a crash
        (["level=1e39"], "level: 1e39 is out of float32's range"),
        (["level=nan"], "level: nan is not a finite number (--allow-nonfinite writes it)"),
        (["level=-inf"], "level: -inf is not a finite number"),
        (["demand_period=inf"], "demand_period: inf is not a number a uint16 can hold"),
        (["demand_period=1e39"], "demand_period: 1e39 is out of range 0..65535 for uint16"),
        (["level=1", "demand_period=5", "level=2"], "level is given twice: write each point once"),
    ],
)
def test_a_value_the_point_cannot_hold_is_refused_and_nothing_sent(
    silent_server, values_map, assignments, words
):
    res = run_cli("write", "-m", values_map, "word=0x10", *assignments, "-p", silent_server.tcp_target)
    assert words in assert_one_error_line(res, 2)
    assert silent_server.received_bytes() == b""


def test_nan_and_inf_are_written_when_the_user_insists(values_map):
    res = expect_ok(
        run_cli(
            "write", "-m", values_map, "level=nan", "total=-inf", "--allow-nonfinite", "--hex", "-p", "sim://"
        )
    )
    sent = [line.data[1:] for line in parse_hex_lines(res.stderr) if line.direction == "TX"]
    assert sent[0][6:10] == bytes([0x7F, 0xC0, 0, 0]) and sent[1][6:14] == bytes([0xFF, 0xF0] + [0] * 6)
    assert res.stdout.splitlines() == ["level nan m", "total -inf"]
    res = run_cli("write-registers", "0", "nan", "--type", "float32", "-p", "sim://")
    assert "nan is not a finite number" in assert_one_error_line(res, 2)
    expect_ok(
        run_cli("write-registers", "0", "nan", "--type", "float32", "--allow-nonfinite", "-p", "sim://")
    )
    res = run_cli("write", "40001", "1e400", "--type", "float64", "--allow-nonfinite", "-p", "sim://")
    assert "1e400 is out of float64's range" in assert_one_error_line(res, 2)


def test_a_float_that_cannot_hold_the_decimal_given_warns_and_shows_what_is_written(values_map):
    res = expect_ok(run_cli("write", "-m", values_map, "level=16777217", "word=0x00FF", "-p", "sim://"))
    assert stderr_lines(res) == [
        "mbtool: warning: level: a float32 cannot hold 16777217; writing 16777216.0 m"
    ]
    assert res.stdout.splitlines() == ["level 16777216.0 m", "word 0x00FF"]
    res = expect_ok(run_cli("write", "-m", values_map, "level=1.5", "demand_period=0x0F", "-p", "sim://"))
    assert res.stderr == "" and res.stdout.splitlines() == ["level 1.5 m", "demand_period 15 min"]


@pytest.mark.parametrize("failing", [1, 2])
def test_the_summary_of_a_failed_write_counts_in_words_that_agree(raw_responder, tmp_path, failing):
    """Issue 39 item 21: a run of two registers whose write got no reply: "2 failed (...:
    they may or may not have been written)", not "it"."""
    saved = tmp_path / "saved.toml"
    run = ", ".join(["5"] * failing)
    saved.write_text(f"sparse = true\n[holding_registers]\n0 = [1]\n10 = [{run}]\n")
    server = raw_responder(TcpPlant(answered=1, then=None))
    line = one_summary(run_cli("restore", saved, *FAST, "-p", server.tcp_target), 3)
    pronoun = "it" if failing == 1 else "they"
    assert line.endswith(
        f"; 1 written (not read back), {failing} failed (no valid reply: {pronoun} may or may not have been written)"
    ), line
