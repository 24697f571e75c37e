"""Where the output goes (issues 12.13, 12.15, 12.16, 13.3, 13.4): CSV appended from cron,
a reader that goes away, -o json on failure, a full disk, a capture cut short."""

from __future__ import annotations

import json
import os
import resource
import shutil
import signal
import subprocess
import sys

import pytest
from helpers.checks import assert_one_error_line
from helpers.run import REPO_ROOT, mbtool_env, run_cli, run_mbtool

pytestmark = pytest.mark.timeout(60)

READ = ("read-holding-registers", "0", "2", "-p", "sim://")


def shell(command: str, timeout: float = 20) -> subprocess.CompletedProcess:
    """A command line as cron or a script runs it: bash, with pipefail."""
    return subprocess.run(
        ["bash", "-o", "pipefail", "-c", command],
        capture_output=True,
        text=True,
        timeout=timeout,
        cwd=REPO_ROOT,
        env=mbtool_env(),
    )


MBTOOL = f"{sys.executable} -m mbtool"


# --- CSV from cron: one header (12.13) ----------------------------------------------------------


def test_csv_appended_to_a_log_keeps_one_header(tmp_path):
    log = tmp_path / "log.csv"
    for _ in range(3):
        assert shell(f"{MBTOOL} {' '.join(READ)} -o csv >> {log}").returncode == 0
    assert log.read_text() == "address,value\n0,0\n1,1\n" + "0,0\n1,1\n" * 2
    for _ in range(2):  # polling too
        assert shell(f"{MBTOOL} {' '.join(READ)} -o csv --polls 1 >> {tmp_path / 'poll.csv'}").returncode == 0
    lines = (tmp_path / "poll.csv").read_text().splitlines()
    assert lines[0] == "time,address,value" and len(lines) == 5 and lines.count("time,address,value") == 1


def test_csv_into_a_new_file_or_a_pipe_has_its_header(tmp_path):
    assert shell(f"{MBTOOL} {' '.join(READ)} -o csv > {tmp_path / 'new.csv'}").returncode == 0
    assert (tmp_path / "new.csv").read_text().startswith("address,value\n")
    assert run_mbtool(*READ, "-o", "csv").stdout.startswith("address,value\n")


def test_no_header_leaves_it_out_always():
    assert run_cli(*READ, "-o", "csv", "--no-header").stdout == "0,0\n1,1\n"
    polled = run_cli(*READ, "-o", "csv", "--no-header", "--polls", "2", "--interval", "0").stdout
    assert len(polled.splitlines()) == 4 and "time" not in polled
    decoded = run_cli("decode", "01 03 00 00 00 02 C4 0B", "-o", "csv", "--no-header").stdout
    assert not decoded.startswith("name,")


# --- -o json: an object for every outcome (12.16) -----------------------------------------------


@pytest.mark.parametrize(
    "args, code",
    [
        (("read-holding-registers", "0", "-p", "tcp://127.0.0.1:1"), 6),
        (("read-holding-registers", "0", "200", "-p", "sim://"), 2),
        (("read-holding-registers", "0", "-p", "sim://", "-u", "7", "-t", "0.2"), 3),
    ],
    ids=["refused", "bad-count", "silent-unit"],
)
def test_a_failed_one_shot_writes_a_json_error_object(args, code):
    res = run_cli(*args, "-o", "json")
    line = assert_one_error_line(res, code)
    assert json.loads(res.stdout) == {"error": line.removeprefix("mbtool: "), "exit_code": code}


def test_polling_json_keeps_its_per_poll_objects_and_no_summary_object():
    res = run_cli("read-holding-registers", "0", "-p", "sim://", "-u", "7", "-t", "0.1", "--polls", "2",
                     "--interval", "0", "-o", "json")  # fmt: skip
    objects = [json.loads(line) for line in res.stdout.splitlines()]
    assert len(objects) == 2 and all(o["exit_code"] == 3 and "time" in o for o in objects)


# --- a reader that goes away (12.15, 13.4) ------------------------------------------------------


@pytest.mark.parametrize("fmt", ["plain", "json", "csv"])
def test_a_closed_pipe_ends_polling_quietly_with_the_sigpipe_status(fmt):
    res = shell(f"{MBTOOL} {' '.join(READ)} --interval 0 -o {fmt} | head -1")
    assert res.returncode == 128 + signal.SIGPIPE, res
    assert res.stderr == "", res.stderr
    assert len(res.stdout.splitlines()) == 1


def test_a_closed_pipe_ends_a_one_shot_quietly():
    res = shell(
        f"{MBTOOL} read-holding-registers 0 125 -p sim:// | head -c 1 >/dev/null; echo ${{PIPESTATUS[0]}}"
    )
    assert res.stdout.strip() in ("0", "141") and res.stderr == "", res  # 0 when it wrote before head left


@pytest.mark.parametrize(
    "args",
    [
        ("read", "40001", "-p", "sim://"),
        ("read-holding-registers", "0", "2", "-p", "sim://", "--polls", "2", "--interval", "0"),
        ("read", "-m", "MAP", "-p", "sim://"),
        ("diff", "DUMP", "-p", "sim://"),
        ("dump", "-", "-p", "sim://"),
        ("read", "40001", "-p", "sim://", "-o", "prom"),
        ("read", "40001", "-p", "sim://", "-o", "influx"),
        ("read", "40001", "-p", "sim://", "-o", "json"),
        ("crc", "01 03"),
    ],
    ids=["read", "polling", "read-map", "diff", "dump", "prom", "influx", "json", "crc"],
)
def test_a_closed_stdout_is_a_reader_gone_not_an_internal_error(args, tmp_path):
    """`>&-` (issue 29.13): nothing can be written, as when the reader of a pipe went away: 141,
    quietly, from every command."""
    (tmp_path / "map.toml").write_text("[points.a]\nref = 40001\n")
    (tmp_path / "dump.toml").write_text("[holding_registers]\n5 = 99\n")
    where = {"MAP": str(tmp_path / "map.toml"), "DUMP": str(tmp_path / "dump.toml")}
    argv = " ".join(f"'{where.get(arg, arg)}'" for arg in args)
    res = shell(f"{MBTOOL} {argv} >&-")
    assert res.returncode == 128 + signal.SIGPIPE, res
    assert "Traceback" not in res.stderr and "internal error" not in res.stderr, res.stderr


@pytest.mark.parametrize("fmt", ["json", "csv"])
def test_a_closed_stderr_is_quiet_and_stdout_carries_data_only(fmt):
    """`2>&-` (issue 40.8): poll's events, failed polls and statistics went into stdout, the
    JSON or CSV stream, and the run crashed (AttributeError, 1). Now they go nowhere, and the
    run ends as it would with stderr open: 8, the spare unit silent, the others answered."""
    res = shell(f"{MBTOOL} poll examples/plant.toml --once -o {fmt} 2>&-")
    assert res.returncode == 8, res
    lines = res.stdout.splitlines()
    if fmt == "json":
        records = [json.loads(line) for line in lines]  # every line an object: no stray text
        assert {r["device"] for r in records} == {"meter1", "plc", "spare"}
    else:
        assert lines[0] == "time,device,name,value,unit,ref" and all(line.count(",") == 5 for line in lines)
    assert "mbtool:" not in res.stdout and "answered" not in res.stdout


def test_a_closed_stderr_keeps_a_failures_exit_status():
    res = shell(f"{MBTOOL} read 40001 -p tcp://127.0.0.1:1 -t 0.2 2>&-")
    assert res.returncode == 6 and res.stdout == "", res


@pytest.mark.parametrize(
    "command, code",
    [
        ("poll examples/plant.toml --once -o json", 8),  # events, statistics, the verdict's line
        ("read 40001 -p tcp://127.0.0.1:1 -t 0.2", 6),  # a failure's one line
        ("decode --framer rtu '01 03 02 00 2a 38 5b'", 5),  # the decoded frame, then its verdict
    ],
    ids=["poll", "read", "decode"],
)
@pytest.mark.parametrize("stderr", ["/dev/full", "a pipe whose reader went away"])
def test_a_stderr_that_cannot_be_written_is_as_a_closed_one(command, code, stderr):
    """A stderr on a full disk (`2>/dev/full`) or a pipe whose reader left: the first line for
    it failed with OSError, and every run ended as an internal error (1), with its data cut
    short and, for a gone reader, as the 141 of stdout's. Lines for the human then go
    nowhere: the data and the exit code are those with stderr open."""
    where = "2>/dev/full" if stderr == "/dev/full" else "2> >(exec 0<&-)"
    opened = shell(f"{MBTOOL} {command}")
    res = shell(f"sleep 0.1; {MBTOOL} {command} {where}")
    assert res.returncode == opened.returncode == code, res
    assert res.stdout.count("\n") == opened.stdout.count("\n") and "mbtool:" not in res.stdout, res


# --- a full disk (13.3) ---------------------------------------------------------------------------


@pytest.mark.parametrize("polling", [(), ("--polls", "50", "--interval", "0")], ids=["one-shot", "polling"])
def test_a_full_disk_is_one_line_and_exit_7(polling):
    res = shell(f"{MBTOOL} {' '.join(READ)} {' '.join(polling)} > /dev/full")
    assert res.returncode == 7, res
    assert res.stderr == "mbtool: cannot write to standard output: No space left on device\n"


def _file_size_limit(size: int):
    def limit() -> None:
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write past the limit fails (EFBIG)
        resource.setrlimit(resource.RLIMIT_FSIZE, (size, size))

    return limit


@pytest.mark.skipif(shutil.which("tshark") is None, reason="tshark reads the capture back")
def test_a_capture_cut_short_ends_on_a_record_and_stays_readable(tmp_path):
    request = bytes.fromhex("01 03 00 00 00 02 C4 0B")
    reply = bytes.fromhex("01 03 04 00 01 00 02 2A 32")
    recording = tmp_path / "line.bin"
    recording.write_bytes((request + reply) * 2000)
    capture = tmp_path / "cut.pcap"
    res = subprocess.run(
        [sys.executable, "-m", "mbtool", "monitor", "--from-file", str(recording), "--capture", str(capture),
         "-o", "json"],
        capture_output=True, text=True, timeout=60, cwd=REPO_ROOT, env=mbtool_env(),
        preexec_fn=_file_size_limit(10_000),
    )  # fmt: skip
    assert res.returncode == 7, res.stderr
    assert res.stderr == f"mbtool: cannot write to capture file {capture}: File too large\n"
    assert 9_000 < os.path.getsize(capture) <= 10_000
    read = subprocess.run(["tshark", "-r", str(capture)], capture_output=True, text=True, timeout=60)
    assert read.returncode == 0 and "cut short" not in read.stderr, read.stderr
    shown = read.stdout.splitlines()
    assert len(shown) > 100 and all("Modbus RTU" in line for line in shown)


# --- small inconsistencies (12.17) ----------------------------------------------------------------


def test_a_polled_table_into_a_file_keeps_every_table_and_ends_its_line(tmp_path):
    out = tmp_path / "tables.txt"
    assert shell(f"{MBTOOL} {' '.join(READ)} -o table --polls 3 --interval 0.01 > {out}").returncode == 0
    text = out.read_text()
    assert text.count("Read Holding Registers · FC 03 (0x03)") == 3 and text.endswith("\n")


def test_write_register_echoes_the_value_in_the_users_type():
    one = json.loads(
        run_cli("write-register", "10", "-5", "--type", "int16", "-p", "sim://", "-o", "json").stdout
    )
    many = json.loads(
        run_cli("write-registers", "10", "-5", "--type", "int16", "-p", "sim://", "-o", "json").stdout
    )
    assert (one["type"], one["values"], one["registers"]) == ("int16", [-5], [65531])
    assert (many["type"], many["values"]) == (one["type"], one["values"])
    assert run_cli("write-register", "10", "-5", "--type", "int16", "-p", "sim://").stdout == "10 -5\n"


def test_a_fraction_for_a_register_names_float32():
    res = run_cli("write-registers", "20", "1.5", "-p", "sim://")
    line = assert_one_error_line(res, 2)
    assert (
        line
        == "mbtool: 1.5 is not a valid register value (a register holds a whole number: for a fraction use --type float32)"
    )


def test_monitor_shows_coils_as_bits_and_exceptions_by_name(tmp_path):
    """As decode does (12.17): not data[0]=205 and exception_code=2."""
    frames = ["01 01 00 00 00 0A BC 0D", "01 01 02 CD 01 2C AC", "01 03 00 00 00 01 84 0A", "01 83 02 C0 F1"]
    recording = tmp_path / "bus.bin"
    recording.write_bytes(bytes.fromhex(" ".join(frames)))
    out = run_cli("monitor", "--from-file", str(recording), "-o", "plain").stdout.splitlines()
    assert "data[0]=0xCD coils 0-7: ON OFF ON ON OFF OFF ON ON" in out[1]
    assert "exception_code=02 Illegal Data Address" in out[3]
    assert "starting_address=0 quantity=1" in out[2]


def test_sub_functions_are_written_one_way():
    """Two hex digits, as function codes are, and the name diag takes: never 15, 000F or 0x0F."""
    assert run_cli("diag", "15", "-p", "sim://").stdout.startswith(
        "sub_function 0F slave-no-response-count\n"
    )
    decoded = run_cli("decode", "01 08 00 0F 00 00 D0 08").stdout
    assert "sub_function 0F slave-no-response-count" in decoded
