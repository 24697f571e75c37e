#!/usr/bin/env python3
"""What a one-shot read costs a cron job, side by side with starting Python and importing click.

Target (issue: foundation): ``mbtool read-holding-registers 0 10 -p tcp://... -o json``
costs at most 1.25 x ``python -c "import click"``.

Starts pymodbus's TCP server (tests/peers/pymodbus_device.py), then runs both
commands alternately, N times each, and prints the medians and their ratio.
Run by hand:  python bench/oneshot.py [-n 40]
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
    args = parser.parse_args()

    # A wheel install compiles .pyc files, as click's were; an editable checkout
    # (or PYTHONDONTWRITEBYTECODE) would otherwise recompile mbtool on every run.
    subprocess.run([sys.executable, "-m", "compileall", "-q", str(ROOT / "mbtool")], check=True)
    port = free_port()
    device = start_device(port)
    # The console script beside this interpreter, not a version manager's shim on PATH
    # (pyenv's shims are bash scripts that would be timed too).
    mbtool = Path(sysconfig.get_path("scripts")) / "mbtool"
    if not mbtool.exists():
        sys.exit(f"bench: {mbtool} not found: install mbtool first (pip install -e .)")
    baseline = [sys.executable, "-c", "import click"]
    oneshot = [
        str(mbtool),
        "read-holding-registers",
        "0",
        "10",
        "-p",
        f"tcp://127.0.0.1:{port}",
        "-o",
        "json",
    ]
    try:
        for command in (baseline, oneshot):  # warm the page cache and .pyc files
            timed(command)
        base, ours = [], []
        for _ in range(args.n):
            base.append(timed(baseline))
            ours.append(timed(oneshot))
    finally:
        device.terminate()
        device.wait(5)

    b, o = statistics.median(base), statistics.median(ours)
    print(f"python -c 'import click'      median {b * 1000:6.1f} ms  (min {min(base) * 1000:.1f})")
    print(f"mbtool read-holding-registers median {o * 1000:6.1f} ms  (min {min(ours) * 1000:.1f})")
    print(f"ratio {o / b:.2f}  (target <= 1.25)   runs {args.n} each, {os.cpu_count()} cores")


if __name__ == "__main__":
    main()
