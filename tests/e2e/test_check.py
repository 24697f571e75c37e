"""``mbtool check`` (issue 17): a monitoring plugin by the Monitoring Plugins guidelines,
against sim:// (holding register i holds i) and pymodbus's server (holding 0..19 = 100..119)."""

from __future__ import annotations

import signal
import subprocess
import sys
import time

import pytest
from helpers.devices import HOLDING
from helpers.run import REPO_ROOT, mbtool_env, run_cli, start_mbtool

pytestmark = pytest.mark.timeout(60)


def check(*args, port="sim://"):
    res = run_cli("check", *args, "-p", port)
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


# --- every outcome a state, one line (issue 29.12) --------------------------------------------
#
# The Nagios plugin API: exactly one line on stdout and an exit code 0-3, whatever happens.
# Anything that keeps check from judging is UNKNOWN (3): bad arguments, a profile or config
# that cannot be used, an output format check does not write, a signal, a stdout that cannot
# be written (the one case with no line: nothing can be written; the reason goes to stderr).


def _config(tmp_path, text: str) -> dict:
    path = tmp_path / "config.toml"
    path.write_text(text)
    return {"MBTOOL_CONFIG": str(path)}


@pytest.mark.parametrize(
    "args, config, words",
    [
        (("40001", "-P", "nosuch"), '[profiles.pump]\nport = "sim://"\n', "no profile nosuch"),
        (("40001", "-P", "pump"), "[profiles.pump\n", "not valid TOML"),
        (("40001", "-P", "pump"), '[profiles.pump]\ncolour = "red"\n', "unknown key"),
        (("40001", "-o", "prom", "-p", "sim://"), "", "no such option -o"),
        (("40001", "-t", "0", "-p", "sim://"), "", "-t"),
    ],
    ids=["no-profile", "broken-config", "bad-profile-key", "prom", "bad-timeout"],
)
def test_what_keeps_check_from_judging_is_unknown_on_one_line(tmp_path, args, config, words):
    res = run_cli("check", *args, env=_config(tmp_path, config))
    assert res.returncode == 3 and res.stderr == "", str(res)
    (line,) = res.stdout.splitlines()
    assert line.startswith("MODBUS UNKNOWN - ") and words in line


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP, signal.SIGINT], ids=lambda s: s.name)
def test_a_signal_is_unknown_on_one_line(silent_server, sig):
    proc = start_mbtool("check", "40001", "-t", "20", "-p", silent_server.tcp_target)
    deadline = time.monotonic() + 15
    while not silent_server.received_bytes(settle=0.05) and time.monotonic() < deadline:
        pass  # until the request is out and check waits for the reply
    proc.send_signal(sig)
    out, err = proc.communicate(timeout=10)
    assert (proc.returncode, out, err) == (3, f"MODBUS UNKNOWN - interrupted by {sig.name}\n", "")


def _shell(command: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        ["bash", "-c", f"{sys.executable} -m mbtool {command}"],
        capture_output=True, text=True, timeout=20, cwd=REPO_ROOT, env=mbtool_env(),
    )  # fmt: skip


@pytest.mark.parametrize(
    "args", ["check 40001 -p sim://", "check --bogus -p sim://", "check 40001 -p tcp://127.0.0.1:1"]
)
@pytest.mark.parametrize(
    "redirect, why",
    [("> /dev/full", "No space left on device"), (">&-", "Broken pipe")],
    ids=["full", "closed"],
)
def test_a_stdout_that_cannot_be_written_is_unknown_with_the_reason_on_stderr(args, redirect, why):
    res = _shell(f"{args} {redirect}")
    assert res.returncode == 3, res
    assert res.stderr == f"mbtool: cannot write the plugin's line to standard output: {why}\n", res.stderr


def test_a_bar_in_a_name_or_unit_never_splits_the_line_or_its_perfdata(tmp_path, tcp_device):
    path = tmp_path / "bars.toml"
    path.write_text('[points."in|out"]\nref = 40001\nunit = "m3|h"\n[points.load]\nref = 40002\nunit = "%"\n')
    code, line = check("-m", path, "-w", "1000", port=tcp_device.target)
    assert code == 0 and line.count("|") == 1
    assert line == "MODBUS OK - inout=100 m3h, load=101 % | inout=100;1000 load=101%;1000"


def test_nan_is_unknown_an_infinity_is_judged_and_neither_breaks_the_perfdata(not_finite):
    code, line = check("-m", not_finite.map, "-w", "30", port=not_finite.target)
    assert code == 3
    assert line == (
        "MODBUS UNKNOWN - nan=nan (UNKNOWN: not a number, nothing to judge), inf=inf (WARNING: outside 0:30), "
        "minus_inf=-inf (WARNING: outside 0:30), fine=21.5 | nan=U;30 inf=U;30 minus_inf=U;30 fine=21.5;30"
    )
    code, _ = check(
        "-m", not_finite.map, "fine", "nan", "--state-on-error", "critical", port=not_finite.target
    )
    assert code == 2


def test_a_point_the_device_refuses_is_judged_as_unreadable_and_the_others_as_read(tmp_path, holed_device):
    path = tmp_path / "holed.toml"
    path.write_text("[device]\nmax_gap = 30\n[points.flow]\nref = 40001\n[points.missing]\nref = 40011\n"
                    "[points.level]\nref = 40021\n")  # fmt: skip
    code, line = check("-m", path, "-w", "150", port=holed_device.target)
    assert code == 3
    assert line.startswith(
        "MODBUS UNKNOWN - flow=100, missing not read (UNKNOWN: exception 02 Illegal Data Address"
    )
    assert line.endswith("), level=200 (WARNING: outside 0:150) | flow=100;150 missing=U;150 level=200;150")
    assert check("-m", path, "-w", "150", "--state-on-error", "warning", port=holed_device.target)[0] == 1


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
