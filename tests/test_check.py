"""``mbtool check`` (issue 17): a monitoring plugin by the Monitoring Plugins guidelines,
against sim:// (holding register i holds i) and pymodbus's server (holding 0..19 = 100..119)."""

from __future__ import annotations

import pytest
from conftest import HOLDING, run_mbtool

pytestmark = pytest.mark.timeout(60)


def check(*args, port="sim://"):
    res = run_mbtool("check", *args, "-p", port)
    lines = res.stdout.splitlines()
    assert len(lines) == 1 and res.stderr == "", str(res)  # one line on stdout, nothing else
    return res.returncode, lines[0]


@pytest.mark.parametrize(
    "ref, ranges, code, why",
    [
        ("40006", ("-w", "10"), 0, ""),  # 5 within 0..10
        ("40021", ("-w", "10"), 1, "outside 0:10"),  # 20 above 10
        ("40006", ("-w", "10:"), 1, "outside 10:"),  # 5 below 10
        ("40021", ("-w", "10:"), 0, ""),
        ("40021", ("-w", "~:10"), 1, "outside ~:10"),  # 20 above 10, no lower end
        ("40006", ("-w", "~:10"), 0, ""),
        ("40016", ("-w", "10:20"), 0, ""),
        ("40026", ("-w", "10:20"), 1, "outside 10:20"),
        ("40016", ("-w", "@10:20"), 1, "inside 10:20"),  # @: alert inside
        ("40026", ("-w", "@10:20"), 0, ""),
        ("40021", ("-w", "10", "-c", "15"), 2, "outside 0:15"),  # critical beats warning
        ("40013", ("-w", "10", "-c", "15"), 1, "outside 0:10"),
    ],
)
def test_every_range_form_and_state(ref, ranges, code, why):
    got, line = check(ref, *ranges)
    assert got == code
    state = ("OK", "WARNING", "CRITICAL")[code]
    value = int(ref) - 40001
    assert line.startswith(f"MODBUS {state} - {ref}={value}")
    assert (f"({state}: {why})" in line) if why else "(" not in line
    perf = line.split(" | ")[1]
    assert perf.startswith(f"{ref}={value};")


def test_perfdata_carries_warning_and_critical_as_given():
    assert check("40006", "-w", "10:20", "-c", "@30:40") == (
        1,
        "MODBUS WARNING - 40006=5 (WARNING: outside 10:20) | 40006=5;10:20;@30:40",
    )


def test_against_pymodbus_several_values_take_the_worst_state(tcp_device):
    code, line = check("40001", "3", "-w", "101", "-c", "101.5", port=tcp_device.target)
    assert code == 2
    assert line == (
        f"MODBUS CRITICAL - 40001={HOLDING[0]}, 40002={HOLDING[1]}, 40003={HOLDING[2]} (CRITICAL: outside 0:101.5)"
        f" | 40001={HOLDING[0]};101;101.5 40002={HOLDING[1]};101;101.5 40003={HOLDING[2]};101;101.5"
    )


@pytest.mark.parametrize(
    "args, words",
    [
        (("40001", "-w", "abc"), "-w abc is not a range"),
        (("40001", "--bogus"), "no such option --bogus"),
        (("40000",), "40001 is holding register 1"),
        ((), "give a reference such as 40011"),
        (("-m", "/nonexistent/map.toml"), "cannot read map"),
    ],
)
def test_bad_arguments_are_unknown(args, words):
    code, line = check(*args)
    assert code == 3 and line.startswith("MODBUS UNKNOWN - ") and words in line


def test_a_device_that_cannot_be_read_is_unknown_unless_told_otherwise(silent_server, tcp_device):
    silent = silent_server.tcp_target
    code, line = check("40001", "-t", "0.2", port=silent)
    assert code == 3 and line.startswith("MODBUS UNKNOWN - no response")
    assert check("40001", "-t", "0.2", "--state-on-error", "critical", port=silent)[0] == 2
    assert check("40001", "-t", "0.2", "--state-on-error", "warning", port=silent)[0] == 1
    code, line = check("41001", port=tcp_device.target)  # past the device's table: exception 02
    assert code == 3 and "exception 02 Illegal Data Address" in line
    code, line = check("40001", port="tcp://127.0.0.1:1")
    assert code == 3 and "cannot connect" in line


def test_map_points_with_their_thresholds_and_the_command_line_beating_them(tmp_path, tcp_device):
    path = tmp_path / "pump.toml"
    path.write_text(
        '[points.flow]\nref = 40001\nscale = 0.1\nunit = "m3/h"\nwarn = "5:9"\ncrit = "2:20"\n'
        '[points.load]\nref = 40002\nunit = "%"\nwarn = 90\n'
        '[points.state]\nref = 40003\nenum = { 102 = "running" }\n'
    )
    code, line = check("-m", path, port=tcp_device.target)
    assert code == 1
    assert line == (
        "MODBUS WARNING - flow=10 m3/h (WARNING: outside 5:9), load=101 % (WARNING: outside 0:90), "
        "state=running | flow=10;5:9;2:20 load=101%;90 state=102"
    )
    code, line = check("-m", path, "flow", "-w", "0:50", port=tcp_device.target)
    assert code == 0 and line == "MODBUS OK - flow=10 m3/h | flow=10;50;2:20"  # 0:50 written as 50
    bad = tmp_path / "bad.toml"
    bad.write_text('[points.x]\nref = 40001\nwarn = "1:x"\n')
    code, line = check("-m", bad, port=tcp_device.target)
    assert code == 3 and "x: warn 1:x is not a range" in line


@pytest.mark.parametrize(
    "ref, ranges, code, why",
    [
        ("40006", ("-w", "110"), 0, ""),  # 105 within 0..110
        ("40019", ("-w", "110"), 1, "outside 0:110"),  # 118 above 110
        ("40006", ("-w", "110:"), 1, "outside 110:"),
        ("40019", ("-w", "110:"), 0, ""),
        ("40019", ("-w", "~:110"), 1, "outside ~:110"),
        ("40006", ("-w", "~:110"), 0, ""),
        ("40016", ("-w", "110:120"), 0, ""),
        ("40006", ("-w", "110:120"), 1, "outside 110:120"),
        ("40016", ("-w", "@110:120"), 1, "inside 110:120"),
        ("40006", ("-w", "@110:120"), 0, ""),
        ("40019", ("-w", "110", "-c", "115"), 2, "outside 0:115"),
    ],
)
def test_every_range_form_and_state_against_pymodbus(tcp_device, ref, ranges, code, why):
    got, line = check(ref, *ranges, port=tcp_device.target)
    assert got == code
    state = ("OK", "WARNING", "CRITICAL")[code]
    value = HOLDING[int(ref) - 40001]
    assert line.startswith(f"MODBUS {state} - {ref}={value}")
    assert (f"({state}: {why})" in line) if why else "(" not in line


# --- ranges that are not: said in the check's own words (issue 28) -------------------------

RANGE_FORMS = "ranges are 10, 10:, ~:10, 10:20 or @10:20"


@pytest.mark.parametrize(
    "option, text, why",
    [
        ("-w", "abc", "abc is not a number"),
        ("-c", "10:abc", "abc is not a number"),
        ("-w", "@x:5", "x is not a number"),
        ("-w", "20:10", "its start 20 is above its end 10"),
        ("-c", "1:2:3", "it has more than one ':'"),
        ("-w", "5:~", "~ is not a number (~ is for the start: ~:10)"),
    ],
)
def test_a_bad_range_says_what_is_wrong(option, text, why):
    code, line = check("40001", option, text)
    assert code == 3
    assert line == f"MODBUS UNKNOWN - {option} {text} is not a range: {why}; {RANGE_FORMS}"


@pytest.mark.parametrize("option", ["-w", "-c"])
def test_a_range_the_shell_made_into_the_home_directory_is_told_to_quote_it(option):
    import os

    home = os.path.expanduser("~")
    code, line = check("40001", option, f"{home}:8000")  # what the shell passes for -w ~:8000
    assert code == 3
    assert line == (
        f"MODBUS UNKNOWN - {option} {home}:8000 is not a range: the shell made ~:8000 into your "
        f"home directory; quote it: {option} '~:8000'"
    )


def test_a_bad_range_in_a_map_names_the_point_and_no_shell(tmp_path):
    import os

    path = tmp_path / "pump.toml"
    path.write_text(f'[points.flow]\nref = 40001\nwarn = "{os.path.expanduser("~")}:8000"\n')
    code, line = check("-m", path, "flow")
    assert code == 3 and line.startswith("MODBUS UNKNOWN - flow: warn ") and "is not a number" in line
    assert "shell" not in line


def test_silence_over_modbus_tcp_is_a_plain_timeout(silent_server):
    # Nothing came back, so nothing says it was a gateway that wants --framer rtu (issue 28).
    code, line = check("40001", "-t", "0.2", port=silent_server.tcp_target)
    assert code == 3 and line == "MODBUS UNKNOWN - no response from unit 1 within 0.2 s"
