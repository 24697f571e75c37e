"""The assertions and waits the tests have in common: one error line and its exit code, the
--hex trace and plain output parsed, a predicate waited for, a socket the peer closed, the
bytecodes a call runs and the attribute reads in it the interpreter left generic.
"""

from __future__ import annotations

import dis
import json
import os
import re
import select
import socket
import subprocess
import sys
import time
from dataclasses import dataclass, field

from helpers.run import Result


def assert_one_error_line(res: Result, code: int) -> str:
    """Exit code as expected, exactly one 'mbtool: ' line on stderr, no traceback. Returns the line."""
    assert res.returncode == code, str(res)
    assert "Traceback" not in res.stderr, str(res)
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1, f"expected exactly one stderr line\n{res}"
    assert lines[0].startswith("mbtool: "), str(res)
    return lines[0]


@dataclass
class HexLine:
    direction: str  # TX or RX
    data: bytes
    verdict: str  # the rest of the line after the hex pairs
    raw: str = field(repr=False, default="")


def parse_hex_lines(stderr: str) -> list[HexLine]:
    """Parse --hex trace lines: 'TX 01 03 ... C5 CD  CRC C5 CD ok'."""
    out = []
    for ln in stderr.splitlines():
        m = re.match(r"^(TX|RX) ((?:[0-9A-F]{2} )*[0-9A-F]{2})(.*)$", ln)
        if m:
            out.append(HexLine(m.group(1), bytes.fromhex(m.group(2)), m.group(3).strip(), ln))
    return out


def plain_pairs(res: Result) -> list[tuple[int, str]]:
    """Plain output 'ADDRESS VALUE' lines as (address, value-text) pairs."""
    pairs = []
    for ln in res.lines:
        parts = ln.split()
        assert len(parts) == 2, f"plain line is not 'ADDRESS VALUE': {ln!r}\n{res}"
        pairs.append((int(parts[0]), parts[1]))
    return pairs


def expect_ok(res: Result) -> Result:
    assert res.returncode == 0, str(res)
    assert "Traceback" not in res.stderr, str(res)
    return res


def wait_until(predicate, deadline: float, step: float = 0.05) -> bool:
    """Whether ``predicate()`` came true within ``deadline`` seconds."""
    end = time.monotonic() + deadline
    while time.monotonic() < end:
        if predicate():
            return True
        time.sleep(step)
    return predicate()


def closed_by_peer(sock: socket.socket, wait: float = 0.0) -> bool:
    """Has the server closed this socket (EOF or reset)?  Reads and discards what is pending."""
    end = time.monotonic() + wait
    while True:
        ready, _, _ = select.select([sock], [], [], max(0.0, end - time.monotonic()))
        if not ready:
            return False
        try:
            if not sock.recv(65536):
                return True
        except (ConnectionResetError, BrokenPipeError):
            return True
        except (BlockingIOError, TimeoutError):
            pass
        if time.monotonic() >= end:
            return False


def json_lines(stdout: str) -> list[dict]:
    return [json.loads(line) for line in stdout.splitlines() if line.strip()]


def bytecodes(call, under: str = "") -> int:
    """The bytecodes ``call()`` runs, in every Python function it calls (on this thread) whose
    file's path starts with ``under`` (a directory, or one file; "": every function): a cost a
    loaded machine does not move, as it moves a time."""
    ran = 0

    def trace(frame, event, arg):
        nonlocal ran
        if not frame.f_code.co_filename.startswith(under):
            return None
        frame.f_trace_opcodes = True
        if event == "opcode":
            ran += 1
        return trace

    sys.settrace(trace)
    try:
        call()
    finally:
        sys.settrace(None)
    return ran


def unspecialized(run, under: str, warm: int = 300, recheck: bool = True) -> list[str]:
    """The attribute reads and writes in the code under ``under`` (a directory) that ``run()``
    runs and the interpreter left generic, after ``warm`` runs to specialize them: a class's
    attribute read on an instance, a named tuple's field, a callable attribute called as a
    method.  Each such read looks the name up in the type and calls its descriptor, some
    hundred instructions where a specialized one (an instance's own attribute, a slot) takes
    a few.  Call it in a fresh interpreter (``in_fresh_interpreter``): code the test process
    ran before with other types may be left generic for a while."""
    for _ in range(warm):
        run()
    ran: dict = {}  # code -> the offsets of its instructions that ran

    def trace(frame, event, arg):
        if not frame.f_code.co_filename.startswith(under):
            return None
        frame.f_trace_opcodes = True
        if event == "opcode":
            ran.setdefault(frame.f_code, set()).add(frame.f_lasti)
        return trace

    sys.settrace(trace)
    try:
        run()
    finally:
        sys.settrace(None)
    generic = ("LOAD_ATTR", "LOAD_METHOD", "STORE_ATTR")  # as the compiler made them: not specialized
    found: dict[str, None] = {}
    # A specialized read whose guess misses every run (an attribute of a split table read by
    # hint) shows as specialized until 3.11 gives it up, 53 misses on, and generic for a while
    # after: looked at after each of as many more runs (untraced: a traced run takes no
    # specialized path), it is seen generic.  ``recheck=False``: looked at once, after the
    # traced run.
    for _ in range(MISSES_BEFORE_GIVING_UP + 1 if recheck else 1):
        if recheck:
            run()
        for code, offsets in ran.items():
            for op in dis.get_instructions(code, adaptive=True):
                if (
                    op.offset in offsets
                    and op.opname.startswith(generic)
                    and (op.opname in generic or op.opname.endswith("_ADAPTIVE"))
                    # A reply's fields written by hand into its record's table (RegistersResponse):
                    # cheaper, measured, than the table set whole or each field by
                    # object.__setattr__.
                    and op.argval != "__dict__"
                ):
                    where = f"{code.co_qualname} ({os.path.basename(code.co_filename)}:{op.positions.lineno})"
                    found[f"{where}: {op.argval}"] = None
    return list(found)


MISSES_BEFORE_GIVING_UP = 53  # CPython 3.11's miss_counter_start(): a specialized op's misses


def in_fresh_interpreter(module: str, function: str) -> list[str]:
    """The lines ``module.function()`` (a test module's, returning a list of lines) returns,
    run in an interpreter of its own."""
    tests = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    here = os.path.join(tests, *module.split(".")[:-1]) if "." in module else tests
    found = subprocess.run(
        [sys.executable, "-c", f"import {module.rsplit('.', 1)[-1]} as m; print(*m.{function}(), sep='\\n')"],
        cwd=here,
        env={**os.environ, "PYTHONPATH": os.pathsep.join((here, tests))},
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert found.returncode == 0, found.stderr
    return found.stdout.strip().splitlines()
