"""A map's values end to end (issues 28 and 29): registers holding NaN and ±Infinity read,
checked, exported and compared without a crash, scaled or not; a map that cannot be used
is refused before the port is opened; labels, and names given without a map.

Peers: ``mbtool serve --data`` holding the float32 bit patterns of NaN and ±Infinity, and
pymodbus's device (tests/peers/pymodbus_device.py), into whose holding registers 900 and
up, which no other test reads, pymodbus's client writes them.
"""

from __future__ import annotations

import json
import math

import pytest
from helpers.checks import assert_one_error_line, expect_ok
from helpers.run import TESTS_DIR, run_cli
from helpers.served import serve
from prometheus_client.parser import text_string_to_metric_families

pytestmark = pytest.mark.timeout(90)

# float32 bit patterns, ABCD: the high word first (IEEE 754: exponent all ones).
PLUS_INF, MINUS_INF, NAN = [0x7F80, 0x0000], [0xFF80, 0x0000], [0x7FC0, 0x0000]

DATA = f"""\
[holding_registers]
0 = {[*PLUS_INF, *MINUS_INF, *NAN, 7, 0x4000, 0x0000, *NAN]}
"""  # 40001 +Inf, 40003 -Inf, 40005 NaN, 40007 = 7, 40008 float32 2.0, 40010 NaN

MAP = """\
[points.hot]
ref = 40001
type = "float32"
scale = 0.1
unit = "C"

[points.cold]
ref = 40003
type = "float32"
scale = -2
offset = 5

[points.fault]
ref = 40005
type = "float32"
scale = 0.1

[points.plain_nan]
ref = 40010
type = "float32"

[points.state]
ref = 40007
enum = { 0 = "stopped", 1 = "running" }

[points.mode]
ref = 40008
type = "float32"
enum = { 0 = "off", 1 = "heat", 2 = "cool" }
"""


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    """mbtool serve holding DATA, and the map of it."""
    where = tmp_path_factory.mktemp("nonfinite")
    (where / "data.toml").write_text(DATA)
    (where / "plant.toml").write_text(MAP)
    with serve("--data", str(where / "data.toml")) as server:
        yield server.target, where / "plant.toml"


def _lines(res) -> list[str]:
    return res.stdout.splitlines()


def test_nan_and_infinity_read_scaled_or_not(served):
    target, plant = served
    res = expect_ok(run_cli("read", "-m", plant, "hot", "cold", "fault", "plain_nan", "-p", target))
    # +Inf x 0.1 is +Inf; -Inf x -2 + 5 is +Inf; NaN stays NaN, scaled or not.
    assert _lines(res) == ["hot inf C", "cold inf", "fault nan", "plain_nan nan"]
    assert res.stderr == ""


def test_nan_and_infinity_as_json_and_prometheus(served):
    target, plant = served
    res = expect_ok(run_cli("read", "-m", plant, "hot", "fault", "-o", "json", "-p", target))
    points = {point["name"]: point for point in json.loads(res.stdout)["points"]}
    assert points["hot"]["registers"] == PLUS_INF and points["fault"]["registers"] == NAN
    res = expect_ok(run_cli("read", "-m", plant, "hot", "cold", "-o", "prom", "-p", target))
    samples = {
        sample.name: sample.value
        for family in text_string_to_metric_families(res.stdout)
        for sample in family.samples
    }
    assert samples.pop("modbus_up") == 1 and samples.pop("modbus_last_success_timestamp_seconds") > 0
    assert samples == {"modbus_hot": math.inf, "modbus_cold": math.inf}


def test_check_judges_infinity_and_cannot_judge_nan(served):
    target, plant = served
    res = run_cli("check", "-m", plant, "hot", "-w", "0:10", "-c", "0:20", "-p", target)
    assert res.returncode == 2 and res.stdout.startswith("MODBUS CRITICAL - hot=inf C"), str(res)
    res = run_cli("check", "-m", plant, "cold", "-w", "10:", "-p", target)
    assert res.returncode == 0 and res.stdout.startswith("MODBUS OK - cold=inf"), str(res)
    for args in (("-m", plant, "fault"), ("-m", plant, "plain_nan"), ("40005", "--type", "float32")):
        res = run_cli("check", *args, "-w", "0:10", "-c", "0:20", "-p", target)
        assert res.returncode == 3, str(res)
        assert res.stdout.startswith("MODBUS UNKNOWN - ") and "not a number" in res.stdout, str(res)
        res = run_cli(
            "check", *args, "-w", "0:10", "-c", "0:20", "--state-on-error", "critical", "-p", target
        )
        assert res.returncode == 2 and res.stdout.startswith("MODBUS CRITICAL - "), str(res)
    # Without thresholds NaN is still no reading to call OK.
    res = run_cli("check", "-m", plant, "fault", "-p", target)
    assert res.returncode == 3 and "not a number" in res.stdout, str(res)


def test_a_nan_among_other_values_sets_the_state(served):
    target, plant = served
    res = run_cli("check", "-m", plant, "state", "fault", "-w", "0:10", "-p", target)
    assert res.returncode == 3, str(res)
    assert res.stdout.startswith("MODBUS UNKNOWN - state=7, fault=nan (UNKNOWN: not a number"), str(res)


def test_diff_of_a_map_point_that_became_infinite(tmp_path):
    before, after, plant = tmp_path / "before.toml", tmp_path / "after.toml", tmp_path / "plant.toml"
    before.write_text("[holding_registers]\n0 = [0, 0, 0, 0]\n")
    after.write_text(f"[holding_registers]\n0 = {[*PLUS_INF, *NAN]}\n")
    plant.write_text(
        '[points.hot]\nref = 40001\ntype = "float32"\nscale = 0.1\n'
        '[points.fault]\nref = 40003\ntype = "float32"\nscale = 0.1\n'
    )
    res = run_cli("diff", before, after, "-m", plant)
    assert res.returncode == 1, str(res)
    assert _lines(res) == ["hot (40001): 0 -> inf", "fault (40003): 0 -> nan"]


def test_nan_written_into_pymodbus_is_unknown_to_check(tcp_device, pymodbus_tcp_client, tmp_path):
    plant = tmp_path / "plant.toml"
    plant.write_text('[points.level]\nref = 40901\ntype = "float32"\nscale = 0.01\nunit = "m"\n')
    assert not pymodbus_tcp_client.write_registers(900, NAN, device_id=1).isError()
    try:
        res = run_cli("check", "-m", plant, "-w", "0:10", "-c", "0:20", "-p", tcp_device.target)
        assert res.returncode == 3 and res.stdout.startswith("MODBUS UNKNOWN - level=nan m"), str(res)
        assert not pymodbus_tcp_client.write_registers(900, MINUS_INF, device_id=1).isError()
        res = run_cli("check", "-m", plant, "-w", "0:10", "-c", "0:20", "-p", tcp_device.target)
        assert res.returncode == 2 and res.stdout.startswith("MODBUS CRITICAL - level=-inf m"), str(res)
        res = expect_ok(run_cli("read", "-m", plant, "-p", tcp_device.target))
        assert _lines(res) == ["level -inf m"]
    finally:
        pymodbus_tcp_client.write_registers(900, [0, 0], device_id=1)


# --- labels ---------------------------------------------------------------------------------


def test_a_value_without_a_label_says_so(served):
    target, plant = served
    res = expect_ok(run_cli("read", "-m", plant, "state", "-p", target))
    assert _lines(res) == ["state 7 (no label)"]
    res = expect_ok(run_cli("read", "-m", plant, "state", "-o", "json", "-p", target))
    assert json.loads(res.stdout)["points"][0]["value"] == 7  # a number for scripts
    rw = plant.parent / "rw.toml"
    rw.write_text(
        MAP.replace('enum = { 0 = "stopped", 1 = "running" }', 'enum = { 0 = "stopped" }\naccess = "rw"')
    )
    res = expect_ok(run_cli("write", "-m", rw, "state=5", "-p", "sim://"))
    assert _lines(res) == ["state 5 (no label)"]
    assert _lines(expect_ok(run_cli("write", "-m", rw, "state=stopped", "-p", "sim://"))) == ["state stopped"]


def test_an_enum_on_a_float32_point(served):
    target, plant = served
    assert _lines(expect_ok(run_cli("read", "-m", plant, "mode", "-p", target))) == ["mode cool"]


# --- a map that cannot be used opens nothing --------------------------------------------------

BAD_MAPS = [
    ("plant.toml", '[points.flow]\nref = 40001\nscale = "1e999999999"\n', "point flow: key scale"),
    ("plant.toml", '[points.flow]\nref = 40001\noffset = "1e5000"\n', "point flow: key offset"),
    ("plant.toml", "[points.flow]\nref = 40001\nunit = " + "[" * 3000 + "]" * 3000, "nested too deeply"),
    ("plant.toml", "[points.t]\nref = 40001\nenum = { 1 = 'a', '0x1' = 'b' }\n", "point t: key enum"),
    ("plant.csv", "name,ref,unit\nflow,40001," + "x" * 140_000 + "\n", "point flow: key unit"),
    ("plant.csv", "name,ref,colour\nflow,40001,\n", "unknown column colour"),
    ("plant.csv", "name,ref,enum\nt,40001,1=a; 1=b\n", "point t: key enum"),
]


@pytest.mark.parametrize("name, text, words", BAD_MAPS, ids=[words for _, _, words in BAD_MAPS])
def test_a_bad_map_is_exit_2_and_nothing_is_opened(silent_server, tmp_path, name, text, words):
    path = tmp_path / name
    path.write_text(text)
    for command in ("read", "write"):
        extra = ("flow=1",) if command == "write" else ()
        res = run_cli(command, "-m", path, *extra, "-p", silent_server.tcp_target)
        line = assert_one_error_line(res, 2)
        assert str(path) in line and words in line, line
    res = run_cli("check", "-m", path, "-p", silent_server.tcp_target)
    assert res.returncode == 3 and str(path) in res.stdout and words in res.stdout, str(res)
    assert silent_server.received_bytes() == b"" and silent_server.connections == 0


# --- names without a map ----------------------------------------------------------------------


@pytest.mark.parametrize("names", [("voltage_l1",), ("voltage_l1", "current_l1"), ("l2",)])
def test_a_name_without_a_map_is_told_about_m(silent_server, names):
    res = run_cli("read", *names, "-p", silent_server.tcp_target)
    line = assert_one_error_line(res, 2)
    assert f"{names[0]} is not a reference" in line and "give its map: -m MAP" in line
    res = run_cli("check", *names, "-p", silent_server.tcp_target)
    assert res.returncode == 3 and "give its map: -m MAP" in res.stdout, str(res)
    assert silent_server.received_bytes() == b"" and silent_server.connections == 0


def test_a_mistyped_reference_is_not_taken_for_a_name(silent_server):
    res = run_cli("read", "4o001", "-p", silent_server.tcp_target)
    line = assert_one_error_line(res, 2)
    assert "a reference has 5 or 6 digits" in line and "-m MAP" not in line


# --- any file nested too deeply: a data file, a dump, the profile file ----------------------


@pytest.mark.parametrize(
    "name, text",
    [
        ("deep.json", '{"holding_registers": ' + "[" * 100_000 + "]" * 100_000 + "}"),
        ("deep.toml", "[holding_registers]\n0 = " + "[" * 5000 + "]" * 5000 + "\n"),
    ],
)
def test_a_data_file_or_dump_nested_too_deeply_is_exit_2(silent_server, tmp_path, name, text):
    path = tmp_path / name
    path.write_text(text)
    res = run_cli("serve", "--data", path, "-p", "tcp://127.0.0.1:0")
    line = assert_one_error_line(res, 2)
    assert str(path) in line and "nested too deeply" in line
    res = run_cli("diff", path, "-p", silent_server.tcp_target)
    line = assert_one_error_line(res, 2)
    assert str(path) in line and "nested too deeply" in line
    assert silent_server.received_bytes() == b"" and silent_server.connections == 0


def test_a_profile_file_nested_too_deeply_is_exit_2(silent_server, tmp_path):
    config = tmp_path / "config.toml"
    config.write_text("[profiles.meter]\nport = " + "[" * 5000 + "]" * 5000 + "\n")
    res = run_cli(
        "read", "40001", "-P", "meter", "-p", silent_server.tcp_target, env={"MBTOOL_CONFIG": str(config)}
    )
    line = assert_one_error_line(res, 2)
    assert str(config) in line and "nested too deeply" in line
    assert silent_server.received_bytes() == b"" and silent_server.connections == 0


def test_a_nan_that_stays_nan_is_no_change(served):
    target, plant = served
    polls = ("--interval", "0.05", "--polls", "3", "--changes", "-p", target)
    for args in (
        ("-m", plant, "fault", "hot"),
        ("40005", "--type", "float32"),
        ("40005", "--type", "float32", "--order", "all"),
    ):
        res = expect_ok(run_cli("read", *args, *polls))
        assert "->" not in res.stdout, str(res)  # NaN equals nothing, itself included
        assert len(_lines(res)) == (2 if "-m" in args else 1), str(res)


def test_read_m_and_check_honour_a_maps_invalid_values(tmp_path):
    """0xFFFF, which the map's [device] invalid names, is no value: never scaled into 6553.5,
    'invalid' in plain, null with invalid true in JSON, no influx field nor Prometheus
    sample, and nothing check can judge (UNKNOWN, or --state-on-error's state) (issue 31)."""
    from line_protocol_parser import parse_line
    from prometheus_client.parser import text_string_to_metric_families

    data = tmp_path / "data.toml"
    data.write_text("[holding_registers]\n0 = [0xFFFF, 230]\n")
    meter = tmp_path / "meter.toml"
    meter.write_text(
        '[device]\ninvalid = [0xFFFF]\n[points.power]\nref = 40001\nscale = 0.1\nunit = "kW"\n'
        '[points.voltage]\nref = 40002\nunit = "V"\n'
    )
    with serve("--data", str(data)) as device:
        read = [
            run_cli("read", "-m", meter, "-o", fmt, "-p", device.target)
            for fmt in ("plain", "json", "influx", "prom")
        ]
        checked = run_cli("check", "-m", meter, "power", "-w", "0:100", "-p", device.target)
        critical = run_cli("check", "-m", meter, "power", "--state-on-error", "critical", "-p", device.target)
    plain, as_json, influx, prom = (res.stdout for res in read)
    assert all(res.returncode == 0 for res in read), read
    assert plain.splitlines() == ["power invalid", "voltage 230 V"]
    power = json.loads(as_json)["points"][0]
    assert power["value"] is None and power["invalid"] is True and power["registers"] == [0xFFFF]
    assert parse_line(influx)["fields"] == {"voltage": 230}
    names = {s.name for family in text_string_to_metric_families(prom) for s in family.samples}
    assert "modbus_voltage" in names and "modbus_power" not in names
    assert checked.returncode == 3 and "power not read (UNKNOWN: no data (invalid))" in checked.stdout
    assert critical.returncode == 2


# --- a point scaled by another (scale_ref): write -m reads the scale factor, then writes ----------

INVERTER = (TESTS_DIR / "data" / "scale-ref-inverter.toml").read_text()


def test_write_m_reads_the_scale_factor_then_writes_in_its_scale(tmp_path):
    data = tmp_path / "data.toml"
    data.write_text("[holding_registers]\n100 = 0\n120 = 0xFFFE\n")  # W_SF -2
    path = tmp_path / "inverter.toml"
    path.write_text(INVERTER)
    with serve("--data", str(data)) as device:
        res = run_cli("write", "-m", path, "W=12.34", "-p", device.target, "-o", "json", "--hex")
        assert res.returncode == 0, res
        written = json.loads(res.stdout)["points"][0]
        assert written["value"] == 12.34 and written["registers"] == [1234]
        back = run_cli("read-holding-registers", "100", "-p", device.target, "-o", "json")
        assert json.loads(back.stdout)["values"] == [1234]
        # The scale factor read first (FC 03 of W_SF alone: W is not read), then FC 06.
        sent = [line.split()[7:12] for line in res.stderr.splitlines() if line.startswith("TX")]
        assert sent == [["01", "03", "00", "78", "00"], ["01", "06", "00", "64", "04"]], res.stderr
        refused = run_cli("write", "-m", path, "W=12.345", "-p", device.target)
        assert refused.returncode == 2 and "not a whole number of steps of 0.01" in refused.stderr
        assert "Traceback" not in refused.stderr
