"""Output for monitoring systems (issue 17): -o influx read back by line-protocol-parser,
-o prom and --textfile by prometheus_client's own text parser."""

from __future__ import annotations

import os
import re
import stat
import subprocess
import sys
import time

import pytest
from helpers.checks import assert_one_error_line, expect_ok
from helpers.devices import COILS, HOLDING, start_device
from helpers.exporter import METER_DATA, METER_MAP
from helpers.prometheus import promtool_check
from helpers.run import run_cli, start_mbtool
from helpers.served import serve
from line_protocol_parser import parse_line
from prometheus_client.parser import text_string_to_metric_families

pytestmark = pytest.mark.timeout(60)

# Names and descriptions that need escaping in both formats.
ODD_MAP = """\
[points."flow rate"]
ref = 40001
scale = 0.5
unit = "m3/h"
description = 'Outlet "main" flow, in \\ out'

[points."a,b=c"]
ref = 40002

[points.state]
ref = 40003
enum = { 102 = "running" }

[points.pump]
ref = "00001"
"""


@pytest.fixture
def odd_map(tmp_path):
    path = tmp_path / "odd.toml"
    path.write_text(ODD_MAP)
    return path


STATUS = ("modbus_up", "modbus_last_success_timestamp_seconds")  # in every exposition


def families(text: str) -> dict:
    return {family.name: family for family in text_string_to_metric_families(text)}


# --- InfluxDB line protocol ------------------------------------------------------------------


def test_influx_one_line_a_read_with_integer_fields_and_a_nanosecond_time(tcp_device):
    res = expect_ok(run_cli("read-holding-registers", "0", "3", "-o", "influx", "-p", tcp_device.target))
    (line,) = res.stdout.splitlines()
    parsed = parse_line(line)
    assert parsed["measurement"] == "modbus" and parsed["tags"] == {"unit": "1", "table": "holding"}
    assert parsed["fields"] == {"0": HOLDING[0], "1": HOLDING[1], "2": HOLDING[2]}
    assert " 0=100i,1=101i,2=102i " in line  # integers carry the i
    assert 1.7e18 < parsed["time"] < 4e18  # nanoseconds since the epoch
    res = expect_ok(run_cli("read", "00001", "2", "-o", "influx", "-p", tcp_device.target))
    parsed = parse_line(res.stdout.strip())
    assert parsed["tags"]["table"] == "coils" and parsed["fields"] == {"00001": COILS[0], "00002": COILS[1]}


def test_influx_escapes_map_names_tags_and_text(tcp_device, odd_map, tmp_path):
    config = tmp_path / "config.toml"
    config.write_text(f'[profiles."pump house, east=2"]\nport = "{tcp_device.target}"\n')
    res = expect_ok(
        run_cli(
            "read",
            "-m",
            odd_map,
            "-o",
            "influx",
            "--measurement",
            "plant modbus,v1",
            "-P",
            "pump house, east=2",
            env={"MBTOOL_CONFIG": str(config)},
        )
    )
    parsed = parse_line(res.stdout.strip())
    assert parsed["measurement"] == "plant modbus,v1"
    assert parsed["tags"] == {"unit": "1", "device": "pump house, east=2"}
    # An enum carries its number, which graphs; a bit is a boolean.
    assert parsed["fields"] == {"flow rate": 50, "a,b=c": HOLDING[1], "state": 102, "pump": True}


def test_influx_polls_one_line_each(tcp_device):
    res = expect_ok(
        run_cli(
            "read-input-registers",
            "0",
            "2",
            "-o",
            "influx",
            "--interval",
            "0",
            "--polls",
            "3",
            "-p",
            tcp_device.target,
        )
    )
    times = [parse_line(line)["time"] for line in res.stdout.splitlines()]
    assert len(times) == 3 and times == sorted(times)


# --- Prometheus text exposition --------------------------------------------------------------


def test_prom_registers_and_bits_as_one_gauge(tcp_device):
    res = expect_ok(run_cli("read-holding-registers", "0", "2", "-o", "prom", "-p", tcp_device.target))
    family = families(res.stdout)["modbus_value"]
    assert family.type == "gauge" and "read by mbtool" in family.documentation
    assert [(s.labels, s.value) for s in family.samples] == [
        ({"unit": "1", "table": "holding", "address": "0"}, HOLDING[0]),
        ({"unit": "1", "table": "holding", "address": "1"}, HOLDING[1]),
    ]


def test_prom_map_points_by_name_with_their_unit_in_help(tcp_device, odd_map):
    res = expect_ok(run_cli("read", "-m", odd_map, "-o", "prom", "-p", tcp_device.target))
    found = families(res.stdout)
    assert set(found) == {"modbus_flow_rate", "modbus_a_b_c", "modbus_state", "modbus_pump", *STATUS}
    flow = found["modbus_flow_rate"]
    assert flow.documentation == 'Outlet "main" flow, in \\ out (m3/h), 40001'
    assert [(s.labels, s.value) for s in flow.samples] == [({"unit": "1", "ref": "40001"}, 50)]
    assert found["modbus_state"].samples[0].value == 102  # an enum by its number
    assert found["modbus_pump"].samples[0].value == 1


def test_the_example_map_as_prom_passes_promtool_and_a_counter_like_name_is_warned_of(tmp_path):
    """A gauge named as a counter (modbus_power_total) is what promtool flags: the example
    map has none, and a map point whose metric ends in _total, _count, _sum or _bucket is
    warned of on stderr, once, before anything is read."""
    with serve("--data", str(METER_DATA)) as meter:
        res = expect_ok(run_cli("read", "-m", METER_MAP, "-o", "prom", "-p", meter.target))
        promtool_check(res.stdout)
        assert "warning" not in res.stderr
        odd = tmp_path / "odd.toml"
        odd.write_text(
            '[points.energy_total]\nref = 30073\ntype = "float32"\n[points.runs_count]\nref = 40001\n'
        )
        res = expect_ok(run_cli("read", "-m", odd, "-o", "prom", "-p", meter.target))
    warnings = [line for line in res.stderr.splitlines() if "warning" in line]
    assert len(warnings) == 2 and "modbus_energy_total, is a gauge" in warnings[0], res.stderr
    assert "ending in _total for counters" in warnings[0] and "ending in _count" in warnings[1]
    assert "modbus_energy_total{" in res.stdout  # still read and written: a warning, not a refusal


def test_textfile_is_written_whole_and_kept_fresh_by_polls(tcp_device, odd_map, tmp_path):
    path = tmp_path / "modbus.prom"
    res = expect_ok(
        run_cli(
            "read",
            "-m",
            odd_map,
            "--textfile",
            path,
            "--interval",
            "0.05",
            "--polls",
            "3",
            "-p",
            tcp_device.target,
        )
    )
    assert res.stdout == ""
    assert "modbus_flow_rate" in families(path.read_text())
    assert sorted(p.name for p in tmp_path.iterdir()) == ["modbus.prom", "odd.toml"]  # no temporary left


@pytest.mark.parametrize(
    "args, words",
    [
        (("diag", "return-query-data", "A537", "-o", "prom"), "-o prom carries values read"),
        (("read", "40001", "--textfile", "x.prom", "-o", "json"), "--textfile writes the Prometheus text"),
        (("read", "40001", "-o", "influx", "--changes", "--polls", "2"), "--changes writes a change log"),
    ],
)
def test_monitoring_formats_refuse_what_they_cannot_carry(silent_server, args, words):
    res = run_cli(*args, "-p", silent_server.tcp_target)
    assert res.returncode == 2 and words in res.stderr
    assert silent_server.received_bytes() == b""


def test_a_text_point_is_a_string_field_and_no_gauge(tcp_device, tmp_path):
    path = tmp_path / "text.toml"
    path.write_text('[points.tag]\nref = 40001\ntype = "string"\ncount = 1\n[points.n]\nref = 40002\n')
    res = expect_ok(run_cli("read", "-m", path, "-o", "influx", "-p", tcp_device.target))
    fields = parse_line(res.stdout.strip())["fields"]
    assert fields == {"tag": "\\x00d", "n": HOLDING[1]}  # 0x0064: a NUL, then "d"
    res = expect_ok(run_cli("read", "-m", path, "-o", "prom", "-p", tcp_device.target))
    assert set(families(res.stdout)) == {"modbus_n", *STATUS}


# --- the textfile's temporary file (issue 29.14) ----------------------------------------------


def test_a_symlink_planted_beside_the_textfile_is_never_followed(tmp_path):
    """The old temporary name was .NAME.PID.tmp: a symlink planted there sent the write to
    another file and then became the textfile itself."""
    from mbtool.cli.sinks import prom as monitoring

    victim = tmp_path / "victim"
    victim.write_text("precious\n")
    path = tmp_path / "modbus.prom"
    for name in (f".modbus.prom.{os.getpid()}.tmp", f".modbus.prom.{os.getpid()}"):
        (tmp_path / name).symlink_to(victim)
    monitoring.write_textfile("modbus_up 1\n", str(path))
    assert victim.read_text() == "precious\n"
    assert not path.is_symlink() and path.read_text() == "modbus_up 1\n"
    # Readable as any file the user makes (node_exporter runs as another user), not 0600.
    umask = os.umask(0)
    os.umask(umask)
    assert stat.S_IMODE(path.stat().st_mode) == 0o666 & ~umask


def test_temporary_files_a_killed_mbtool_left_are_cleaned_up(tcp_device, tmp_path):
    path = tmp_path / "modbus.prom"
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    stale = tmp_path / f".modbus.prom.{dead.pid}.k3x9_q2a.tmp"  # as SIGKILL leaves one
    stale.write_text("half")
    live = tmp_path / f".modbus.prom.{os.getpid()}.a1b2c3d4.tmp"  # another writer, still at it
    live.write_text("half")
    other = tmp_path / ".other.prom.1.tmp"  # not this textfile's
    other.write_text("x")
    expect_ok(run_cli("read", "40001", "--textfile", path, "-p", tcp_device.target))
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(["modbus.prom", live.name, other.name])


# --- names the line protocol must carry (issue 29.11) -----------------------------------------


def reference_unescaped(text: str) -> str:
    """The line-protocol reference reads two contiguous backslashes as one (the first is an
    escape); line_protocol_parser keeps both, so the test applies that rule itself."""
    return text.replace("\\\\", "\\")


def test_backslashes_never_swallow_the_separator_after_them(tcp_device, tmp_path):
    path = tmp_path / "slash.toml"
    path.write_text(
        "[points.'a\\']\nref = 40001\n[points.'b\\\\c']\nref = 40002\n[points.'e\\,f']\nref = 40003\n"
    )
    config = tmp_path / "config.toml"
    config.write_text(f"[profiles.'east\\x']\nport = \"{tcp_device.target}\"\n")
    res = expect_ok(
        run_cli(
            "read", "-m", path, "-o", "influx", "--measurement", "m\\x", "-P", "east\\x",
            env={"MBTOOL_CONFIG": str(config)},
        )
    )  # fmt: skip
    parsed = parse_line(res.stdout.strip())
    assert reference_unescaped(parsed["measurement"]) == "m\\x"
    assert {k: reference_unescaped(v) for k, v in parsed["tags"].items()} == {
        "unit": "1",
        "device": "east\\x",
    }
    fields = {reference_unescaped(key): value for key, value in parsed["fields"].items()}
    assert fields == {"a\\": HOLDING[0], "b\\\\c": HOLDING[1], "e\\,f": HOLDING[2]}


@pytest.mark.parametrize(
    "args, words",
    [
        (("-P", "line\nbreak"), "profile 'line\\nbreak': a tag or label is written on one line"),
        (
            ("--measurement", "line\nbreak"),
            "--measurement 'line\\nbreak': a measurement is written on one line",
        ),
        (("--measurement", ""), "--measurement '': a measurement has a name"),
        (("--measurement", "#modbus"), "--measurement '#modbus': a line starting with # is a comment"),
        (("--measurement", "modbus\\"), "a backslash at the end of a measurement escapes the separator"),
        (("-P", "east\\"), "a backslash at the end of a tag or label escapes the separator"),
    ],
    ids=["profile", "measurement", "empty", "comment", "backslash", "tag-backslash"],
)
def test_names_the_line_protocol_cannot_carry_are_refused_before_anything_is_sent(
    silent_server, tmp_path, args, words
):
    config = tmp_path / "config.toml"
    config.write_text(
        f'[profiles."line\\nbreak"]\nport = "{silent_server.tcp_target}"\n'
        f"[profiles.'east\\']\nport = \"{silent_server.tcp_target}\"\n"
    )
    res = run_cli(
        "read", "40001", "-o", "influx", *args, *([] if "-P" in args else ["-p", silent_server.tcp_target]),
        env={"MBTOOL_CONFIG": str(config)},
    )  # fmt: skip
    assert words in assert_one_error_line(res, 2)
    assert res.stdout == "" and silent_server.received_bytes() == b""


# --- a field's type, for ever (issue 28, 3) ----------------------------------------------------


def test_a_points_field_type_is_fixed_by_its_map_entry_whatever_the_value(tmp_path):
    """InfluxDB refuses a field whose type changes: a scaled point that reads 0.3 once and 1.0
    the next is a float both times, never 1i (sim://: holding register i holds i)."""
    path = tmp_path / "types.toml"
    path.write_text(
        "[points.scaled_fraction]\nref = 40004\nscale = 0.1\n"  # 3 -> 0.3
        "[points.scaled_whole]\nref = 40011\nscale = 0.1\n"  # 10 -> 1.0, not 1i
        "[points.offset_whole]\nref = 40012\noffset = 0.5\n[points.offset_whole2]\nref = 40013\noffset = 1\n"
        "[points.counter]\nref = 40014\n"  # an integer: always i
        "[points.label]\nref = 40015\nenum = { 14 = 'on' }\n"  # an enum carries its raw number
        "[points.float]\nref = 40101\ntype = 'float32'\n"  # 21.5
    )
    res = expect_ok(run_cli("read", "-m", path, "-o", "influx", "-p", "sim://"))
    fields = parse_line(res.stdout.strip())["fields"]
    assert fields == {
        "scaled_fraction": 0.3,
        "scaled_whole": 1.0,
        "offset_whole": 11.5,
        "offset_whole2": 13.0,
        "counter": 13,
        "label": 14,
        "float": 21.5,
    }
    kinds = {name: type(value) for name, value in fields.items()}
    assert kinds == {**dict.fromkeys(fields, float), "counter": int, "label": int}


# --- values that are not numbers (issue 28, 3) ---------------------------------------------------


def test_influx_leaves_a_value_that_is_not_a_number_out_with_a_warning(not_finite):
    res = expect_ok(run_cli("read", "-m", not_finite.map, "-o", "influx", "-p", not_finite.target))
    assert parse_line(res.stdout.strip())["fields"] == {"fine": 21.5}
    assert res.stderr.splitlines() == [
        f"mbtool: warning: {name} ({ref}) reads {value}: left out of the InfluxDB line (it has no NaN or infinity)"
        for name, ref, value in (
            ("nan", "40001", "nan"),
            ("inf", "40003", "inf"),
            ("minus_inf", "40005", "-inf"),
        )
    ]
    # Registers as well as points; and polling warns once a value, not once a poll.
    res = expect_ok(
        run_cli(
            "read", "40001", "4", "--type", "float32", "-o", "influx", "--polls", "3", "--interval", "0",
            "-p", not_finite.target,
        )
    )  # fmt: skip
    assert [parse_line(line)["fields"] for line in res.stdout.splitlines()] == [{"40007": 21.5}] * 3
    assert [line for line in res.stderr.splitlines() if "warning" in line] == [
        f"mbtool: warning: holding {ref} reads {value}: left out of the InfluxDB line (it has no NaN or infinity)"
        for ref, value in (("40001", "nan"), ("40003", "inf"), ("40005", "-inf"))
    ]


def test_a_read_with_no_number_to_write_writes_no_influx_line(not_finite):
    """A line with no fields is no point: InfluxDB refuses the whole write."""
    res = expect_ok(
        run_cli("read", "-m", not_finite.map, "nan", "inf", "-o", "influx", "-p", not_finite.target)
    )
    assert res.stdout == "" and len(res.stderr.splitlines()) == 2


def test_json_and_prom_carry_what_is_not_a_number_as_they_can(not_finite):
    import json

    res = expect_ok(run_cli("read", "-m", not_finite.map, "-o", "json", "-p", not_finite.target))
    values = {p["name"]: p["value"] for p in json.loads(res.stdout)["points"]}
    assert values == {"nan": None, "inf": None, "minus_inf": None, "fine": 21.5}
    res = expect_ok(run_cli("read", "-m", not_finite.map, "-o", "prom", "-p", not_finite.target))
    found = families(res.stdout)
    assert [
        str(found[f"modbus_{name}"].samples[0].value) for name in ("nan", "inf", "minus_inf", "fine")
    ] == [
        "nan",
        "inf",
        "-inf",
        "21.5",
    ]


# --- one missing point (issue 28, 3) ------------------------------------------------------------

# pymodbus's holed device (tests/peers/pymodbus_device.py HOLED): holding 0-9 hold 100-109,
# 20-29 hold 200-209, and 10-19 do not exist (exception 02). max_gap 30 merges the three
# points into one read, 40001-40021, which the device refuses.
HOLED_MAP = """\
[device]
max_gap = 30
[points.flow]
ref = 40001
[points.missing]
ref = 40011
[points.level]
ref = 40021
"""

PARTIAL = 8  # the exit code of a read that got some points and not others


@pytest.fixture
def holed_map(tmp_path):
    path = tmp_path / "holed.toml"
    path.write_text(HOLED_MAP)
    return path


def test_one_missing_point_no_longer_blanks_out_the_map_read(holed_device, holed_map):
    res = run_cli("read", "-m", holed_map, "-o", "plain", "-p", holed_device.target)
    assert res.stdout == "flow 100\nlevel 200\n"
    line = assert_one_error_line(res, PARTIAL)
    assert "missing (40011): exception 02 Illegal Data Address" in line and "2 of 3 points read" in line


def test_json_names_the_point_it_could_not_read_in_its_one_object(holed_device, holed_map):
    import json

    res = run_cli("read", "-m", holed_map, "-o", "json", "-p", holed_device.target)
    assert_one_error_line(res, PARTIAL)
    data = json.loads(res.stdout)  # one object: the failure is in it, not a second one
    assert [(p["name"], p["value"]) for p in data["points"]] == [("flow", 100), ("level", 200)]
    (failed,) = data["failed"]
    assert (failed["name"], failed["ref"]) == ("missing", "40011")
    assert failed["error"].startswith("exception 02 Illegal Data Address")


def test_the_monitoring_outputs_export_the_points_read(holed_device, holed_map):
    res = run_cli("read", "-m", holed_map, "-o", "influx", "-p", holed_device.target)
    assert res.returncode == PARTIAL
    assert parse_line(res.stdout.strip())["fields"] == {"flow": 100, "level": 200}
    res = run_cli("read", "-m", holed_map, "-o", "prom", "-p", holed_device.target)
    assert res.returncode == PARTIAL
    found = families(res.stdout)
    assert found["modbus_flow"].samples[0].value == 100 and found["modbus_level"].samples[0].value == 200
    assert "modbus_missing" not in found


def test_a_refused_merged_read_is_split_once_and_stays_split_while_polling(holed_device, holed_map):
    res = run_cli(
        "read", "-m", holed_map, "-o", "plain", "--polls", "3", "--interval", "0", "--hex",
        "-p", holed_device.target,
    )  # fmt: skip
    assert res.returncode == PARTIAL, res
    assert [line.split(" ", 1)[1] for line in res.stdout.splitlines()] == ["flow 100", "level 200"] * 3
    sent = [line for line in res.stderr.splitlines() if line.startswith("TX")]
    # The merged read once, refused; then each point alone, every poll.
    assert len(sent) == 1 + 3 * 3, res.stderr
    failures = [line for line in res.stderr.splitlines() if re.search(r" poll \d+: ", line)]
    assert len(failures) == 3 and all("missing (40011): exception 02" in line for line in failures)
    # Each poll got some of its points: partial, not an error, in the summary.
    assert ", replies 0, partial 3, timeouts 0, errors 0," in res.stderr.splitlines()[-1]


# --- a device that cannot be read (issue 28, 3) -----------------------------------------------


def status(found: dict) -> tuple[float, float | None]:
    """modbus_up's value, and modbus_last_success_timestamp_seconds's (None when absent)."""
    up = found["modbus_up"].samples[0]
    assert up.labels == {"unit": "1"}
    last = found.get("modbus_last_success_timestamp_seconds")
    return up.value, last.samples[0].value if last else None


def test_prom_says_the_device_answered_and_when(tcp_device):
    before = time.time()
    res = expect_ok(run_cli("read-holding-registers", "0", "2", "-o", "prom", "-p", tcp_device.target))
    up, last = status(families(res.stdout))
    assert up == 1 and before <= last <= time.time()


def test_a_textfile_of_a_device_that_cannot_be_read_says_so_and_keeps_no_stale_value(
    tcp_device, refused_port, tmp_path
):
    path = tmp_path / "modbus.prom"
    expect_ok(run_cli("read", "40001", "2", "--textfile", path, "-p", tcp_device.target))
    _, answered = status(families(path.read_text()))
    res = run_cli("read", "40001", "2", "--textfile", path, "-p", f"tcp://127.0.0.1:{refused_port}")
    assert res.returncode == 6 and res.stdout == ""
    found = families(path.read_text())
    assert set(found) == set(STATUS)  # modbus_value is gone: no stale value is scraped as current
    assert status(found) == (0, answered)  # the last success, from the file it replaced


def test_prom_on_stdout_says_the_device_cannot_be_read(silent_server):
    res = run_cli("read", "40001", "-o", "prom", "-t", "0.2", "-p", silent_server.tcp_target)
    assert res.returncode == 3
    found = families(res.stdout)
    assert set(found) == {"modbus_up"} and status(found) == (0, None)  # no success to tell of


def test_a_polled_textfile_follows_the_device_down(tmp_path):

    path = tmp_path / "modbus.prom"
    with start_device(tcp=True, framer="socket", units="1") as device:
        proc = start_mbtool(
            "read",
            "40001",
            "--textfile",
            path,
            "--interval",
            "0.1",
            "--polls",
            "600",
            "-t",
            "0.2",
            "-p",
            device.target,
        )
        try:
            found = _wait_for(path, lambda found: status(found)[0] == 1)
            assert found["modbus_value"].samples[0].value == HOLDING[0]
        except BaseException:
            proc.kill()
            raise
    try:
        stopped = time.time()
        found = _wait_for(path, lambda found: status(found)[0] == 0)
        assert set(found) == set(STATUS)
        assert stopped - 5 < status(found)[1] <= stopped
    finally:
        proc.kill()
        proc.communicate(timeout=10)


def _wait_for(path, condition, wait: float = 20.0) -> dict:
    deadline = time.monotonic() + wait
    while time.monotonic() < deadline:
        if path.exists():
            found = families(path.read_text())
            if "modbus_up" in found and condition(found):
                return found
        time.sleep(0.05)
    raise AssertionError(
        f"{path} never showed what was awaited: {path.read_text() if path.exists() else None}"
    )


@pytest.mark.parametrize(
    "name, measurement", [("up", "modbus"), ("last_success_timestamp_seconds", "plant")], ids=["up", "last"]
)
def test_a_point_named_as_a_status_metric_is_refused_before_anything_is_sent(
    silent_server, tmp_path, name, measurement
):
    path = tmp_path / "status.toml"
    path.write_text(f"[points.{name}]\nref = 40001\n")
    res = run_cli(
        "read", "-m", path, "-o", "prom", "--measurement", measurement, "-p", silent_server.tcp_target
    )
    assert f"its metric, {measurement}_{name}, is the one that says" in assert_one_error_line(res, 2)
    assert silent_server.received_bytes() == b""
