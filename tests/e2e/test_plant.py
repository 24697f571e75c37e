"""The plant's language end to end (issue 15): Modicon references (read, write, write-bit),
register maps (read -m, write -m), --order all and a profile's map, against sim://,
mbtool serve and pymodbus's server, over TCP and over a pseudo-terminal.

pymodbus's device (tests/peers/pymodbus_device.py) holds holding registers 0..19 =
100..119, input registers 0..19 = 200..219, coils alternating from on, discrete inputs
on; its tables end at 999.  The session's devices are shared: writes here go to
addresses 500 and up, which no other test reads.
"""

from __future__ import annotations

import json
import struct
from pathlib import Path

import pytest
from helpers.checks import assert_one_error_line, expect_ok, parse_hex_lines
from helpers.devices import COILS, HOLDING, INPUT
from helpers.ptys import PTY_SERIAL_OPTS, PtyPair
from helpers.run import REPO_ROOT, run_cli
from helpers.served import pymodbus_tcp, serve

pytestmark = pytest.mark.timeout(60)

PUMP = """\
[device]
max_gap = 4

[points.speed]
ref = 40001
scale = 0.1
unit = "rpm"
description = "Motor speed"

[points.mode]
ref = 40002
enum = { 101 = "auto", 102 = "manual" }

[points.flag3]
ref = 40003
bit = 1

[points.pressure]
ref = 30005
scale = 0.5
offset = -2
unit = "bar"

[points.running]
ref = "00001"

[points.setpoint]
ref = 40501
scale = 0.1
unit = "m3/h"
access = "rw"

[points.level]
ref = 40511
type = "float32"
order = "CDAB"
unit = "m"
access = "rw"

[points.state]
ref = 40513
enum = { 0 = "stopped", 1 = "running", 2 = "fault" }
access = "rw"

[points.alarm]
ref = 40521
bit = 3
access = "rw"

[points.pump_on]
ref = "00601"
access = "rw"
"""


@pytest.fixture
def pump(tmp_path) -> Path:
    path = tmp_path / "pump.toml"
    path.write_text(PUMP)
    return path


def tcp(device, *args, **kw):
    return run_cli(*args, "-p", device.target, **kw)


def lines(res) -> list[str]:
    return res.stdout.splitlines()


# --- Modicon references ---------------------------------------------------------------------


def test_read_by_reference_names_each_item_by_its_reference(tcp_device):
    res = expect_ok(tcp(tcp_device, "read", "40001", "3"))
    assert lines(res) == [f"4000{i + 1} {HOLDING[i]}" for i in range(3)]
    res = expect_ok(tcp(tcp_device, "read", "30002", "2", "-o", "json"))
    data = json.loads(res.stdout)
    assert data["function"] == 4 and data["values"] == INPUT[1:3]
    assert data["addresses"] == [1, 2] and data["refs"] == ["30002", "30003"]
    res = expect_ok(tcp(tcp_device, "read", "00001", "4"))
    assert lines(res) == [f"0000{i + 1} {int(COILS[i])}" for i in range(4)]
    res = expect_ok(tcp(tcp_device, "read", "10003"))
    assert lines(res) == ["10003 1"]


@pytest.mark.parametrize("ref", ["40003", "400003", "4x0003", "4X00003"])
def test_every_form_of_a_reference_reads_the_same_register(tcp_device, ref):
    res = expect_ok(tcp(tcp_device, "read", ref, "-o", "json"))
    assert json.loads(res.stdout)["values"] == [HOLDING[2]]
    assert json.loads(res.stdout)["addresses"] == [2]


def test_read_by_reference_with_a_type_polls_and_traces(tcp_device):
    res = expect_ok(
        tcp(tcp_device, "read", "40001", "2", "--type", "uint32", "--polls", "2", "--interval", "0")
    )
    values = [line.split()[1:] for line in lines(res)]
    expected_first = HOLDING[0] << 16 | HOLDING[1]
    assert values == [["40001", str(expected_first)], ["40003", str(HOLDING[2] << 16 | HOLDING[3])]] * 2
    res = expect_ok(tcp(tcp_device, "read", "40011", "--hex"))
    (tx,) = [line for line in parse_hex_lines(res.stderr) if line.direction == "TX"]
    assert tx.data[-5:] == bytes([0x03, 0x00, 0x0A, 0x00, 0x01])  # FC03, address 10, count 1


def test_write_by_reference_picks_the_function_code(tcp_device, pymodbus_tcp_client):
    res = expect_ok(tcp(tcp_device, "write", "40601", "17", "--hex"))
    assert lines(res) == ["40601 17"]
    assert _functions_sent(res) == [0x06]
    res = expect_ok(tcp(tcp_device, "write", "40602", "5", "--multiple", "--hex"))
    assert _functions_sent(res) == [0x10]
    res = expect_ok(tcp(tcp_device, "write", "40603", "7", "8", "--hex"))
    assert _functions_sent(res) == [0x10] and lines(res) == ["40603 7", "40604 8"]
    regs = pymodbus_tcp_client.read_holding_registers(600, count=4, device_id=1).registers
    assert regs == [17, 5, 7, 8]
    res = expect_ok(tcp(tcp_device, "write", "00611", "on", "--hex"))
    assert _functions_sent(res) == [0x05]
    res = expect_ok(tcp(tcp_device, "write", "00612", "on", "--multiple", "--hex"))
    assert _functions_sent(res) == [0x0F]
    assert pymodbus_tcp_client.read_coils(610, count=2, device_id=1).bits[:2] == [True, True]
    res = expect_ok(tcp(tcp_device, "write", "40621", "1.5", "--type", "float32", "--order", "CDAB"))
    regs = pymodbus_tcp_client.read_holding_registers(620, count=2, device_id=1).registers
    assert struct.unpack(">f", struct.pack(">HH", regs[1], regs[0]))[0] == 1.5


def _functions_sent(res) -> list[int]:
    # MBAP: the function code follows the 7-byte header.
    return [line.data[7] for line in parse_hex_lines(res.stderr) if line.direction == "TX"]


@pytest.mark.parametrize(
    "args, words",
    [
        (("read", "40000"), "40001 is holding register 1"),
        (("read", "1"), "a reference has 5 or 6 digits: 00001 for coil 1"),
        (("read", "20001"), "no table has the prefix 2"),
        (("read", "flow"), "give its map: -m MAP"),
        (("read", "40001", "2", "3"), "points by name need -m MAP"),
        (("read",), "give a reference such as 40001"),
        (("read", "00001", "--type", "float32"), "--type is for registers; 00001 is coil 1"),
        (("read", "40001", "--order", "all"), "--order all shows 32- and 64-bit values"),
        (("write", "30001", "5"), "input registers are read-only"),
        (("write", "10001", "on"), "discrete inputs are read-only"),
        (("write", "40001", "70000"), "out of range"),
        (("write", "00001", "maybe"), "not a bit"),
        (("write", "40001"), "give a reference and a value"),
        (("write-bit", "30001", "3", "on"), "write-bit changes a bit of a holding register"),
        (("write-bit", "40001", "16", "on"), "16"),
        (("write-bit", "40001", "3", "maybe"), "not a bit"),
    ],
)
def test_an_invalid_reference_or_value_is_exit_2_with_nothing_sent(silent_server, args, words):
    res = run_cli(*args, "-p", f"tcp://127.0.0.1:{silent_server.port}")
    line = assert_one_error_line(res, 2)
    assert words in line
    assert silent_server.received_bytes() == b""


def test_the_per_function_commands_keep_wire_addresses(tcp_device):
    # 40001 means holding register 40001 to read-holding-registers: no reinterpretation.
    res = tcp(tcp_device, "read-holding-registers", "40001")
    assert res.returncode == 4 and "Illegal Data Address" in res.stderr
    assert lines(expect_ok(tcp(tcp_device, "read-holding-registers", "1"))) == [f"1 {HOLDING[1]}"]


# --- --order all ----------------------------------------------------------------------------


def test_order_all_shows_each_word_order_side_by_side():
    # sim:// holds 21.5 as ABCD at 100-101 and as CDAB at 102-103.
    res = expect_ok(run_cli("read", "40101", "2", "--type", "float32", "--order", "all", "-p", "sim://"))
    first, second = (dict(part.split("=") for part in line.split()[1:]) for line in lines(res))
    assert first["ABCD"] == "21.5" and second["CDAB"] == "21.5"
    assert set(first) == {"ABCD", "CDAB", "BADC", "DCBA"}
    res = expect_ok(
        run_cli(
            "read-holding-registers",
            "100",
            "2",
            "--type",
            "float32",
            "--order",
            "all",
            "-o",
            "csv",
            "-p",
            "sim://",
        )
    )
    assert lines(res)[0] == "address,ABCD,CDAB,BADC,DCBA"
    assert lines(res)[1].split(",")[1] == "21.5" and lines(res)[2].split(",")[2] == "21.5"
    res = expect_ok(
        run_cli("read", "40101", "2", "--type", "float32", "--order", "all", "-o", "json", "-p", "sim://")
    )
    data = json.loads(res.stdout)
    assert data["order"] == "all" and data["values"][0]["ABCD"] == 21.5 and data["values"][1]["CDAB"] == 21.5


# --- register maps: read --------------------------------------------------------------------


def test_a_map_reads_names_values_and_units(tcp_device, pump):
    res = expect_ok(tcp(tcp_device, "read", "-m", pump, "speed", "mode", "flag3", "pressure", "running"))
    assert lines(res) == [
        f"speed {HOLDING[0] / 10:g} rpm",
        "mode auto",  # the register holds 101
        f"flag3 {'on' if HOLDING[2] >> 1 & 1 else 'off'}",
        f"pressure {INPUT[4] * 0.5 - 2:g} bar",
        "running on",
    ]


def test_a_map_read_as_json_carries_ref_unit_and_raw_registers(tcp_device, pump):
    res = expect_ok(tcp(tcp_device, "read", "-m", pump, "speed", "pressure", "running", "-o", "json"))
    data = json.loads(res.stdout)
    assert data["unit"] == 1 and data["map"] == str(pump)
    speed, pressure, running = data["points"]
    assert speed == {"name": "speed", "value": 10, "unit": "rpm", "ref": "40001", "registers": [HOLDING[0]]}
    assert pressure["value"] == INPUT[4] * 0.5 - 2 and pressure["ref"] == "30005"
    assert running == {"name": "running", "value": True, "ref": "00001", "bits": [True]}


def test_a_map_read_as_json_leaves_out_the_unit_of_a_point_without_one(tcp_device, pump):
    # A point's "unit" is its engineering unit; an empty one read as the record's unit id
    # gone missing.  Left out, as poll -o json leaves it out; the record's own "unit" is
    # the unit id, a number, alone or polled.
    for extra in ((), ("--interval", "0", "--polls", "2")):
        res = expect_ok(tcp(tcp_device, "read", "-m", pump, "running", "speed", "-o", "json", *extra))
        for line in res.stdout.splitlines():
            record = json.loads(line)
            assert record["unit"] == 1
            running, speed = record["points"]
            assert "unit" not in running and speed["unit"] == "rpm"


def test_a_map_read_as_csv_and_polled(tcp_device, pump):
    res = expect_ok(tcp(tcp_device, "read", "-m", pump, "speed", "mode", "-o", "csv"))
    assert lines(res) == ["name,value,unit,ref,registers", "speed,10,rpm,40001,100", "mode,auto,,40002,101"]
    res = expect_ok(tcp(tcp_device, "read", "-m", pump, "speed", "--polls", "3", "--interval", "0"))
    assert [line.split(" ", 1)[1] for line in lines(res)] == ["speed 10 rpm"] * 3
    assert "polls 3, replies 3" in res.stderr


def test_a_map_reads_close_points_in_one_request(tcp_device, pump):
    # speed, mode and flag3 are holding registers 0-2: one FC03; pressure an FC04; running an FC01.
    res = expect_ok(
        tcp(tcp_device, "read", "-m", pump, "speed", "mode", "flag3", "pressure", "running", "--hex")
    )
    assert sorted(_functions_sent(res)) == [0x01, 0x03, 0x04]


def test_a_merged_read_refused_with_exception_02_is_retried_point_by_point(tcp_device, tmp_path):
    # The device's tables end at 999: a block 990-1005 is refused, 990 alone is not.
    path = tmp_path / "edge.toml"
    path.write_text("[device]\nmax_gap = 20\n[points.inside]\nref = 40991\n[points.outside]\nref = 41006\n")
    res = tcp(tcp_device, "read", "-m", path, "inside", "--hex")
    assert res.returncode == 0 and lines(res) == ["inside 0"]
    # The point the device refuses is that point's failure; the other is read (exit 8, partial).
    res = tcp(tcp_device, "read", "-m", path)
    line = assert_one_error_line(res, 8)
    assert "outside (41006)" in line and "Illegal Data Address" in line and lines(res) == ["inside 0"]
    res = tcp(tcp_device, "read", "-m", path, "--hex")
    assert res.returncode == 8
    # The merged read, then each point alone.
    sent = [line.data[-4:] for line in parse_hex_lines(res.stderr) if line.direction == "TX"]
    assert [struct.unpack(">HH", pdu) for pdu in sent] == [(990, 16), (990, 1), (1005, 1)]


FIFTY = {
    # table: (references of the points, type): 50 points over the four tables
    "coils": ([f"{60 * i + 1:05d}" for i in range(15)], None),  # coils 0..840: one FC01 (2000 bits)
    "discrete": ([f"1{i + 1:04d}" for i in range(5)], None),  # one FC02
    "input": ([f"3{30 * i + 1:04d}" for i in range(10)], "uint16"),  # 0..270: 271 > 125, two FC04
    "holding": ([f"4{12 * i + 1:04d}" for i in range(20)], "float32"),  # 0..229: 230 > 125, two FC03
}


def test_fifty_points_over_four_tables_take_the_fewest_requests_the_limits_allow(tcp_device, tmp_path):
    """Reads never cross tables (4 at least); the input points span 271 registers and the
    holding ones 230, over the 125 one read may carry (spec §3): two reads each.  So 6."""
    text = "[device]\nmax_gap = 2000\n"
    for table, (refs, kind) in FIFTY.items():
        for i, ref in enumerate(refs):
            text += f'[points.{table}{i}]\nref = "{ref}"\n' + (f'type = "{kind}"\n' if kind else "")
    path = tmp_path / "fifty.toml"
    path.write_text(text)
    res = expect_ok(tcp(tcp_device, "read", "-m", path, "--hex", "-o", "json"))
    assert len(json.loads(res.stdout)["points"]) == 50
    assert sorted(_functions_sent(res)) == [0x01, 0x02, 0x03, 0x03, 0x04, 0x04]
    values = {point["name"]: point["value"] for point in json.loads(res.stdout)["points"]}
    assert (
        values["coils0"] is True
        and values["input3"] == 0
        and values["holding0"]
        == pytest.approx(struct.unpack(">f", struct.pack(">HH", HOLDING[0], HOLDING[1]))[0])
    )


def test_a_map_comes_from_a_profile_beside_the_config_file(tcp_device, tmp_path):
    (tmp_path / "pump.toml").write_text(PUMP)
    config = tmp_path / "config.toml"
    config.write_text(f'[profiles.pump]\nport = "{tcp_device.target}"\nmap = "pump.toml"\n')
    res = expect_ok(run_cli("read", "-P", "pump", "speed", env={"MBTOOL_CONFIG": str(config)}))
    assert lines(res) == ["speed 10 rpm"]


def test_a_map_with_type_options_or_unknown_names_is_exit_2(tcp_device, pump, tmp_path):
    res = tcp(tcp_device, "read", "-m", pump, "--type", "float32")
    assert "--type does not apply with -m" in assert_one_error_line(res, 2)
    res = tcp(tcp_device, "read", "-m", pump, "speed", "flow")
    assert "no point named flow" in assert_one_error_line(res, 2)
    bad = tmp_path / "bad.toml"
    bad.write_text('[points.x]\nref = 40001\ntype = "float32"\nbit = 2\n')
    res = tcp(tcp_device, "read", "-m", bad)
    line = assert_one_error_line(res, 2)
    assert str(bad) in line and "point x" in line and "bit" in line


# --- register maps: write -------------------------------------------------------------------


def test_a_map_writes_in_engineering_units(tcp_device, pump, pymodbus_tcp_client):
    res = expect_ok(
        tcp(
            tcp_device,
            "write",
            "-m",
            pump,
            "setpoint=22.5",
            "level=1.25",
            "state=running",
            "pump_on=on",
            "--hex",
        )
    )
    assert lines(res) == ["setpoint 22.5 m3/h", "level 1.25 m", "state running", "pump_on on"]
    assert _functions_sent(res) == [0x06, 0x10, 0x06, 0x05]
    assert pymodbus_tcp_client.read_holding_registers(500, count=1, device_id=1).registers == [225]
    low, high = pymodbus_tcp_client.read_holding_registers(510, count=2, device_id=1).registers
    assert struct.unpack(">f", struct.pack(">HH", high, low))[0] == 1.25  # CDAB: low word first
    assert pymodbus_tcp_client.read_holding_registers(512, count=1, device_id=1).registers == [1]
    assert pymodbus_tcp_client.read_coils(600, count=1, device_id=1).bits[0] is True
    res = expect_ok(tcp(tcp_device, "read", "-m", pump, "setpoint", "level", "state"))
    assert lines(res) == ["setpoint 22.5 m3/h", "level 1.25 m", "state running"]


@pytest.mark.parametrize(
    "assignment, words",
    [
        ("setpoint=22.53", "the nearest writable values are 22.5 and 22.6"),
        ("speed=100", "speed (40001) is not writable: the map does not mark it rw"),
        ("state=broken", "broken is none of stopped, running, fault"),
        ("alarm=maybe", "maybe is not on or off"),
        ("setpoint=7000", "out of range"),
        ("setpoint", "write a point as NAME=VALUE"),
        ("flow=1", "no point named flow"),
    ],
)
def test_an_invalid_map_write_is_exit_2_with_nothing_sent(silent_server, pump, assignment, words):
    # The valid first assignment is not sent either: every value is checked first.
    res = run_cli(
        "write", "-m", pump, "setpoint=1", assignment, "-p", f"tcp://127.0.0.1:{silent_server.port}"
    )
    assert words in assert_one_error_line(res, 2)
    assert silent_server.received_bytes() == b""


def test_a_bit_is_written_with_mask_write_register(tcp_device, pump, pymodbus_tcp_client):
    pymodbus_tcp_client.write_register(520, 0x00F8, device_id=1)
    res = expect_ok(tcp(tcp_device, "write", "-m", pump, "alarm=off", "--hex"))
    assert _functions_sent(res) == [0x16] and lines(res) == ["alarm off"]
    assert pymodbus_tcp_client.read_holding_registers(520, count=1, device_id=1).registers == [0x00F0]
    res = expect_ok(tcp(tcp_device, "write-bit", "40521", "0", "on", "--hex"))
    tx = [line.data for line in parse_hex_lines(res.stderr) if line.direction == "TX"]
    assert [d[7:] for d in tx] == [bytes([0x16, 0x02, 0x08, 0xFF, 0xFE, 0x00, 0x01])]  # AND ~bit0, OR bit0
    assert pymodbus_tcp_client.read_holding_registers(520, count=1, device_id=1).registers == [0x00F1]


def test_a_device_without_fc22_names_rmw_and_rmw_writes_the_bit():
    with serve("--exception", "22:1") as server:
        target = f"tcp://{server.host}:{server.port}"
        client = pymodbus_tcp(server)
        try:
            client.write_register(30, 0x1000, device_id=1)
            res = run_cli("write-bit", "40031", "2", "on", "-p", target)
            line = assert_one_error_line(res, 4)
            assert "exception 01 Illegal Function" in line and "--rmw" in line
            res = expect_ok(run_cli("write-bit", "40031", "2", "on", "--rmw", "--hex", "-p", target))
            assert _functions_sent(res) == [0x03, 0x06]
            assert "not atomic" in res.stderr
            assert client.read_holding_registers(30, count=1, device_id=1).registers == [0x1004]
            res = expect_ok(run_cli("write-bit", "40031", "12", "off", "--rmw", "-p", target))
            assert client.read_holding_registers(30, count=1, device_id=1).registers == [0x0004]
        finally:
            client.close()


def test_map_and_references_against_mbtool_serve(pump):
    with serve() as server:
        target = f"tcp://{server.host}:{server.port}"
        expect_ok(run_cli("write", "-m", pump, "setpoint=12.3", "alarm=on", "-p", target))
        client = pymodbus_tcp(server)
        try:
            assert client.read_holding_registers(500, count=1, device_id=1).registers == [123]
            assert client.read_holding_registers(520, count=1, device_id=1).registers[0] & 0x08
        finally:
            client.close()
        res = expect_ok(run_cli("read", "-m", pump, "setpoint", "alarm", "-p", target))
        assert lines(res) == ["setpoint 12.3 m3/h", "alarm on"]
        res = expect_ok(run_cli("read", "40101", "--type", "float32", "-p", target))
        assert lines(res) == ["40101 21.5"]


def test_map_and_references_on_sim(pump):
    res = expect_ok(run_cli("read", "-m", pump, "speed", "running", "-p", "sim://"))
    assert lines(res) == ["speed 0 rpm", "running on"]
    res = expect_ok(
        run_cli("write", "-m", pump, "setpoint=1", "state=fault", "--dry-run", "-p", "sim://", "-o", "plain")
    )
    # Both frames shown (setpoint 1 m3/h is raw 10 at 500, state fault is 2 at 512), none sent.
    raws = [line for line in lines(res) if line.startswith("raw ")]
    assert [raw[4:21] for raw in raws] == ["01 06 01 F4 00 0A", "01 06 02 00 00 02"]


# --- over a pseudo-terminal -----------------------------------------------------------------


def test_references_and_maps_over_a_serial_line(serial_rtu_device, pump):
    def ser(*args):
        return run_cli(*args, "-p", serial_rtu_device.target, *PTY_SERIAL_OPTS)

    assert lines(expect_ok(ser("read", "40002", "2"))) == [f"40002 {HOLDING[1]}", f"40003 {HOLDING[2]}"]
    assert lines(expect_ok(ser("read", "-m", pump, "speed", "pressure"))) == [
        "speed 10 rpm",
        f"pressure {INPUT[4] * 0.5 - 2:g} bar",
    ]
    expect_ok(ser("write", "-m", pump, "setpoint=4.2", "alarm=on"))
    assert lines(expect_ok(ser("read", "-m", pump, "setpoint", "alarm"))) == ["setpoint 4.2 m3/h", "alarm on"]
    assert lines(expect_ok(ser("write-bit", "40521", "3", "off"))) == ["40521 bit 3 off"]


def test_the_readme_energy_meter_reads_as_the_readme_shows():
    """The meter of docs/maps-and-references.md's "Register maps" (once in the README)."""
    meter = REPO_ROOT / "examples/energy-meter.toml"
    with serve("--data", str(REPO_ROOT / "examples/energy-meter-data.toml")) as server:
        target = f"tcp://{server.host}:{server.port}"
        res = expect_ok(run_cli("read", "-m", meter, "--hex", "-p", target))
        assert lines(res) == [
            "voltage_l1 230.1 V",
            "current_l1 12.5 A",
            "active_power 8625.0 W",
            "frequency 50.0 Hz",
            "energy_import 15342.7 kWh",
            "tariff day",
            "demand_period 15 min",
            "ct_ratio 100 A",
            "overload on",
            "relay on",
        ]
        assert len(_functions_sent(res)) == 6  # as docs/maps-and-references.md says
        res = expect_ok(run_cli("read", "30001", "--type", "float32", "--order", "all", "-p", target))
        assert "CDAB=230.1" in res.stdout
        res = run_cli("write", "-m", meter, "ct_ratio=102", "-p", target)
        assert "the nearest writable values are 100 and 105" in assert_one_error_line(res, 2)


@pytest.mark.parametrize("example", ["energy-meter.toml"])
def test_an_example_maps_header_commands_read_its_twin(example):
    """The commands an example's header says to try, run as written (but for the port):
    its twin served with the data file it names, then read with the map."""
    header = [
        row[1:].strip()
        for row in (REPO_ROOT / "examples" / example).read_text().splitlines()
        if row.startswith("#")
    ]
    commands = [row.removesuffix("&").split() for row in header if row.startswith("mbtool ")]
    (serve_argv,) = [argv[2:] for argv in commands if argv[1] == "serve"]
    (read_argv,) = [argv[1:] for argv in commands if argv[1] == "read"]
    at = serve_argv.index("-p")
    del serve_argv[at : at + 2]  # the test picks the port
    with serve(*serve_argv) as server:
        at = read_argv.index("-p")
        read_argv[at + 1] = f"tcp://{server.host}:{server.port}"
        assert lines(expect_ok(run_cli(*read_argv)))[0] == "voltage_l1 230.1 V"


def test_a_map_write_may_broadcast_but_rmw_may_not(pump, silent_server):
    res = expect_ok(run_cli("write", "-m", pump, "setpoint=1", "-u", "0", "-p", "sim://"))
    assert lines(res) == ["setpoint 1 m3/h"] and "broadcast: no device confirms" in res.stderr
    res = run_cli("write-bit", "40001", "1", "on", "--rmw", "-u", "0", "-p", silent_server.socket_target)
    assert "--rmw, which reads the register first, needs a unit 1..255" in assert_one_error_line(res, 2)
    assert silent_server.received_bytes() == b""


def test_a_csv_map_from_a_spreadsheet_reads_like_a_toml_one(tcp_device, tmp_path):
    path = tmp_path / "pump.csv"
    path.write_text(
        "name,ref,type,scale,unit,enum,bit\n"
        "speed,40001,,0.1,rpm,,\n"
        "mode,40002,,,,101=auto; 102=manual,\n"
        "flag3,40003,,,,,1\n"
        "running,00001,,,,,\n"
    )
    res = expect_ok(tcp(tcp_device, "read", "-m", path))
    assert lines(res) == ["speed 10 rpm", "mode auto", "flag3 on", "running on"]


def test_a_map_read_as_a_table_names_value_unit_ref_and_raw(tcp_device, pump):
    res = expect_ok(tcp(tcp_device, "read", "-m", pump, "speed", "running", "-o", "table"))
    header = next(line for line in lines(res) if "Name" in line)
    assert [word for word in header.replace("┃", " ").split()] == [
        "Name",
        "Value",
        "Unit",
        "Ref",
        "Raw",
        "Description",
    ]
    speed = next(line for line in lines(res) if "speed" in line)
    assert speed.replace("│", " ").split() == ["speed", "10", "rpm", "40001", "0064", "Motor", "speed"]


def test_references_maps_and_bits_against_mbtool_serve_over_a_serial_line(pump):

    pair = PtyPair()
    try:
        with serve("--parity", "N", target=pair.device_path):

            def ser(*args):
                return run_cli(*args, "-p", pair.mbtool_path, *PTY_SERIAL_OPTS)

            expect_ok(ser("write", "-m", pump, "setpoint=7.5", "state=fault"))
            assert lines(expect_ok(ser("read", "-m", pump, "setpoint", "state"))) == [
                "setpoint 7.5 m3/h",
                "state fault",
            ]
            assert lines(expect_ok(ser("read", "40101", "--type", "float32"))) == ["40101 21.5"]
            assert lines(expect_ok(ser("write-bit", "40521", "2", "on"))) == ["40521 bit 2 on"]
            assert lines(expect_ok(ser("read", "-m", pump, "alarm"))) == ["alarm off"]  # bit 3, not 2
    finally:
        pair.close()
