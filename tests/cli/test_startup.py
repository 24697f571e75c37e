"""What a one-shot read loads at start-up: only what that read uses (issue 41, point 9).

A cron job's read pays for every module it imports and every object it builds before it
sends its request; bench/oneshot.py --instructions measures the whole.  These tests hold the
cuts measured there: each names what a read no longer loads or builds, in a fresh process.
"""

from __future__ import annotations

import json
import subprocess
import sys
import tomllib
from pathlib import Path

# Run in a fresh interpreter: the read, then at exit what it loaded, as JSON on stderr's last line.
READ_AND_REPORT = """
import atexit, json, sys
def report():
    print(json.dumps(sorted(sys.modules)), file=sys.__stderr__)
atexit.register(report)
from mbtool.cli import main
sys.argv = ["mbtool", *sys.argv[1:]]
main()
"""


def loaded_by(*args: str) -> set[str]:
    """The modules a one-shot ``mbtool ARGS`` has loaded when it ends (it must succeed)."""
    result = subprocess.run(
        [sys.executable, "-c", READ_AND_REPORT, *args], capture_output=True, text=True, timeout=30
    )
    assert result.returncode == 0, result.stderr
    return set(json.loads(result.stderr.splitlines()[-1]))


def test_a_tcp_read_connects_without_the_socket_module(tcp_device):
    """socket.py costs 12 M instructions (its enums), 5 % of a one-shot read: a TCP connection
    is made from _socket alone, as the transports' numbers are."""
    loaded = loaded_by("read-holding-registers", "0", "10", "-p", tcp_device.target, "-o", "json")
    assert "mbtool.link.transport" in loaded  # the read did go over TCP
    assert "socket" not in loaded


def test_a_read_sets_its_stop_signals_without_the_signal_module():
    """signal.py turns every signal, handler and mask into an enum on import: 3 M instructions.
    main's stop signals (the errors' STOP_SIGNALS) are _signal's numbers and handlers."""
    assert "signal" not in loaded_by("read-holding-registers", "0", "10", "-p", "sim://", "-o", "json")


# A read as above, counting the --port options click made on the way.
COUNT_PORT_OPTIONS = """
import atexit, sys, click
made = []
init = click.Parameter.__init__
def counted(self, *args, **kwargs):
    init(self, *args, **kwargs)
    made.append(self.name)
click.Parameter.__init__ = counted
atexit.register(lambda: print(made.count("port"), file=sys.__stderr__))
from mbtool.cli import main
sys.argv = ["mbtool", *sys.argv[1:]]
main()
"""


def test_a_read_makes_the_link_options_of_its_own_command_only():
    """read.py holds five commands, each with some forty options: click makes an option object
    in 50 k instructions, and a read parses one command's.  The link's options (--port, the
    serial line's, TLS's...) of a device command are made when it is run or shown, not when its
    module is imported."""
    result = subprocess.run(
        [sys.executable, "-c", COUNT_PORT_OPTIONS, "read-holding-registers", "0", "2", "-p", "sim://"],
        capture_output=True,
        text=True,
        timeout=30,
    )
    assert result.returncode == 0, result.stderr
    assert result.stderr.splitlines()[-1] == "1"


# A read as above, naming at exit each regular expression mbtool's own code compiled.
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
    read = ["read-holding-registers", "0", "10", "-p", serial_rtu_device.target, "-o", "json"]
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
        [sys.executable, "-c", COUNT_START_UP_COLLECTIONS, "read-holding-registers", "0", "2", "-p", "sim://"],
        capture_output=True,
        text=True,
        timeout=30,
    )
    assert result.returncode == 0, result.stderr
    assert result.stderr.splitlines()[-1] == "0 True"
    with open(Path(__file__).parents[2] / "pyproject.toml", "rb") as project:
        assert tomllib.load(project)["project"]["scripts"]["mbtool"] == "mbtool.__main__:run"
