#!/usr/bin/env python3
"""What a one-shot read costs a cron job, side by side with starting Python and importing click.

Target (issues: foundation, fast where it counts, 30): ``mbtool read-holding-registers 0 10
-o json`` from a TCP device, from the built-in ``sim://`` and from an RTU device on a serial
line, each costs at most 1.25 x ``python -c "import click"``.

Starts pymodbus's TCP server (tests/peers/pymodbus_device.py) and ``mbtool serve`` on one end
of a pseudo-terminal pair (the tests' virtual null-modem cable, tests/helpers/ptys.py), then runs
the commands alternately, N times each, and prints the medians and their ratio.
With ``--before DIR`` (a checkout of an earlier commit, e.g. from ``git worktree add``)
the same reads are timed from that tree too, in the same loop, so a change's start-up
cost is measured against the tree it changes rather than against another day's noise.
With ``--instructions`` each command runs once under valgrind's callgrind instead, and the
instructions it executed are printed: a figure that does not move with the machine's load
(the time a command waits for its device is not in it).

Run by hand:  python bench/oneshot.py [-n 40] [--before /tmp/before] [--instructions]
"""

from __future__ import annotations

import argparse
import os
import socket
import statistics
import subprocess
import sys
import sysconfig
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))

from helpers.ptys import PTY_SERIAL_OPTS, PtyPair  # noqa: E402
from polling_instructions import instructions  # noqa: E402


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start_device(port: int) -> subprocess.Popen:
    device = subprocess.Popen(
        [sys.executable, str(ROOT / "tests/peers/pymodbus_device.py"), "--tcp", f"127.0.0.1:{port}"],
        stdout=subprocess.PIPE,
        text=True,
    )
    deadline = time.monotonic() + 15
    while time.monotonic() < deadline:
        if device.stdout.readline().strip() == "READY":
            return device
    device.kill()
    sys.exit("bench: the pymodbus device did not start")


def start_serial_device(mbtool: Path, where: str) -> subprocess.Popen:
    """``mbtool serve`` on the serial line ``where``: an RTU device, ready once it says so."""
    device = subprocess.Popen(
        [str(mbtool), "serve", "-p", where, *PTY_SERIAL_OPTS, "-q"], stdout=subprocess.PIPE, text=True
    )
    if not device.stdout.readline().startswith("serving"):
        device.kill()
        sys.exit("bench: mbtool serve did not start")
    return device


def timed(command: list[str]) -> float:
    start = time.perf_counter()
    result = subprocess.run(command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    elapsed = time.perf_counter() - start
    if result.returncode:
        sys.exit(f"bench: {' '.join(command)} failed: {result.stderr.decode().strip()}")
    return elapsed


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("-n", type=int, default=40, help="runs of each command")
    parser.add_argument(
        "--before",
        type=Path,
        action="append",
        default=[],
        help="an earlier checkout to time side by side (repeatable)",
    )
    parser.add_argument(
        "--instructions", action="store_true", help="count each command's instructions with callgrind, once"
    )
    args = parser.parse_args()

    # A wheel install compiles .pyc files, as click's were; an editable checkout
    # (or PYTHONDONTWRITEBYTECODE) would otherwise recompile mbtool on every run.
    trees = [ROOT] + [tree.resolve() for tree in args.before]
    for tree in trees:
        subprocess.run([sys.executable, "-m", "compileall", "-q", str(tree / "mbtool")], check=True)
    # The console script beside this interpreter, not a version manager's shim on PATH
    # (pyenv's shims are bash scripts that would be timed too).
    mbtool = Path(sysconfig.get_path("scripts")) / "mbtool"
    if not mbtool.exists():
        sys.exit(f"bench: {mbtool} not found: install mbtool first (pip install -e .)")
    port = free_port()
    device = start_device(port)
    line = PtyPair()
    serial_device = start_serial_device(mbtool, line.device_path)
    baseline = [sys.executable, "-c", "import click"]
    read = ["read-holding-registers", "0", "10", "-o", "json"]
    reads = {
        "TCP": [*read, "-p", f"tcp://127.0.0.1:{port}"],
        "sim://": [*read, "-p", "sim://"],
        "RTU": [*read, "-p", line.mbtool_path, *PTY_SERIAL_OPTS],
    }
    commands = {"python -c 'import click'": baseline}
    for name, arguments in reads.items():
        commands[f"mbtool read-holding-registers ({name})"] = [str(mbtool), *arguments]
    if args.before:
        # Both trees started the same way, as python -m mbtool (what the console script runs,
        # whichever function a tree's entry point names), with the tree first on the path.
        launcher = (
            "import runpy, sys; sys.path.insert(0, sys.argv.pop(1)); "
            "runpy.run_module('mbtool', run_name='__main__', alter_sys=True)"
        )
        for tree in trees:
            for name, arguments in reads.items():
                commands[f"the {name} read from {tree}"] = [
                    sys.executable,
                    "-c",
                    launcher,
                    str(tree),
                    *arguments,
                ]
    times: dict[str, list[float]] = {label: [] for label in commands}
    counts: dict[str, int] = {}
    try:
        for command in commands.values():  # warm the page cache and .pyc files
            timed(command)
        if args.instructions:
            counts = {label: instructions(command) for label, command in commands.items()}
        for _ in range(0 if args.instructions else args.n):
            for label, command in commands.items():
                times[label].append(timed(command))
    finally:
        for peer in (device, serial_device):
            peer.terminate()
            peer.wait(5)
        line.close()

    if counts:
        base = counts["python -c 'import click'"]
        for label, count in counts.items():
            print(f"{label:50} {count / 1e6:8.1f} M instructions  ratio {count / base:.2f}")
        return
    medians = {label: statistics.median(runs) for label, runs in times.items()}
    base = medians["python -c 'import click'"]
    for label, runs in times.items():
        print(
            f"{label:50} median {medians[label] * 1000:6.1f} ms  (min {min(runs) * 1000:.1f})"
            f"  ratio {medians[label] / base:.2f}"
        )
    print(f"target: each read <= 1.25 x import click   runs {args.n} each, {os.cpu_count()} cores")


if __name__ == "__main__":
    main()
