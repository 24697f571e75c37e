"""A one-shot read's start-up (issue 41.9: at most 1.25 x ``python -c "import click"``,
bench/oneshot.py --instructions): it makes each shared option once, and it imports neither
the socket module nor the signal module, whose enums cost more than the read itself; a clean
read compiles no regular expression, and the script imports the command line with the cyclic
collector off."""

from __future__ import annotations

import subprocess
import sys
import tomllib
from pathlib import Path

import click
import pytest
from helpers.ptys import PTY_SERIAL_OPTS

from mbtool.cli.program import cli


def _imported_by_a_read(target: str) -> set[str]:
    code = (
        "import sys; from mbtool.cli import main; sys.argv = ['mbtool', 'read-holding-registers', '0', '3',"
        f" '-p', {target!r}, '-o', 'json', '-t', '0.3'];\n"
        "import atexit; atexit.register(lambda: print(' '.join(sorted(sys.modules)), file=sys.stderr))\n"
        "main()"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=30)
    return set(result.stderr.split())


@pytest.mark.parametrize("target", ["sim://", "tcp://127.0.0.1:1"])  # port 1: refused, after the connect
def test_a_one_shot_read_imports_neither_socket_nor_signal(target):
    imported = _imported_by_a_read(target)
    assert "mbtool.cli.commands.read" in imported
    assert "socket" not in imported and "signal" not in imported


def _command(name: str) -> click.Command:
    with click.Context(cli) as ctx:
        command = cli.get_command(ctx, name)
    assert command is not None
    return command


def _param(command: click.Command, name: str) -> click.Parameter:
    return next(param for param in command.params if param.name == name)


def test_the_commands_of_a_module_share_their_link_options_and_scan_keeps_its_own_timeout():
    read, coils, scan, ping = (
        _command(name) for name in ("read-holding-registers", "read-coils", "scan", "ping")
    )
    assert _param(read, "port") is _param(coils, "port")  # made once
    assert _param(read, "value_type") is _param(_command("read-input-registers"), "value_type")
    assert _param(scan, "timeout").default == 0.2 and "each unit's reply" in (
        _param(scan, "timeout").help or ""
    )
    for other in (read, coils, ping):  # scan's change is scan's alone
        assert _param(other, "timeout").default == 1.0
        assert "each unit's reply" not in (_param(other, "timeout").help or "")


# A one-shot mbtool ARGS, naming at exit each regular expression mbtool's own code compiled.
MBTOOL_PATTERNS = """
import atexit, re, sys, traceback
compiled = []
compile_ = re._compile
def traced(pattern, flags):
    callers = [frame.filename for frame in traceback.extract_stack()[:-1]]
    if any("/mbtool/" in caller for caller in callers[-3:]):
        compiled.append(repr(pattern))
    return compile_(pattern, flags)
re._compile = traced
atexit.register(lambda: print(compiled, file=sys.__stderr__))
from mbtool.cli import main
sys.argv = ["mbtool", *sys.argv[1:]]
main()
"""


def patterns_compiled_by(*args: str) -> str:
    result = subprocess.run(
        [sys.executable, "-c", MBTOOL_PATTERNS, *args], capture_output=True, text=True, timeout=30
    )
    assert result.returncode == 0, result.stderr
    return result.stderr.splitlines()[-1]


def test_a_clean_sim_read_compiles_no_pattern():
    """A regular expression costs 0.5 to 2.5 M instructions to compile.  The target's look-alike
    check (is this serial device name a host?) and the RTU framers' resync marks (where a frame
    may start amid garbage) are compiled when a read first needs them: a clean read never does."""
    assert patterns_compiled_by("read-holding-registers", "0", "10", "-p", "sim://", "-o", "json") == "[]"


def test_a_clean_serial_read_compiles_no_pattern(serial_rtu_device):
    # No parity, as every test on a pseudo-terminal: once a test has opened it with none, it
    # refuses 8E1 (EINVAL), so this test passed only as the first on its worker's line.
    read = [
        "read-holding-registers",
        "0",
        "10",
        "-p",
        serial_rtu_device.target,
        *PTY_SERIAL_OPTS,
        "-o",
        "json",
    ]
    assert patterns_compiled_by(*read) == "[]"


# python -m mbtool, counting the collector's passes that run before the command's module is
# imported (by main, as it parses the command line): the start-up's.
COUNT_START_UP_COLLECTIONS = """
import gc, runpy, sys
passes = []
def counted(phase, info):
    if phase == "start" and "mbtool.cli.commands.read" not in sys.modules:
        passes.append(info["generation"])
gc.callbacks.append(counted)
sys.argv = ["mbtool", *sys.argv[1:]]
try:
    runpy.run_module("mbtool", run_name="__main__")
finally:
    print(len(passes), gc.isenabled(), file=sys.__stderr__)
"""


def test_the_script_imports_the_command_line_with_the_collector_off():
    """Start-up allocates some hundred thousand objects and frees almost none: the cyclic
    collector's passes over them (8 M instructions) find nothing.  The script (python -m
    mbtool, and the mbtool entry point, the same function) imports the command line with the
    collector off; main freezes what start-up built and turns it on for the run."""
    result = subprocess.run(
        [
            sys.executable,
            "-c",
            COUNT_START_UP_COLLECTIONS,
            "read-holding-registers",
            "0",
            "2",
            "-p",
            "sim://",
        ],
        capture_output=True,
        text=True,
        timeout=30,
    )
    assert result.returncode == 0, result.stderr
    assert result.stderr.splitlines()[-1] == "0 True"
    with open(Path(__file__).parents[2] / "pyproject.toml", "rb") as project:
        assert tomllib.load(project)["project"]["scripts"]["mbtool"] == "mbtool.__main__:run"
