#!/usr/bin/env python3
"""Sustained polling: mbtool's transactions per second beside pymodbus's synchronous client.

Target (issue: field tools): polling 10 holding registers back to back
(``--interval 0``) over TCP loopback, mbtool at least matches pymodbus's
synchronous client doing the same reads in a loop against the same server.
On a serial line a transaction should cost the wire time plus the required
silences and little else: over a pseudo-terminal (which carries bytes at once,
so the wire time is nil) the cost above one t3.5 silence is mbtool's overhead.

Both peers poll the same pymodbus server (tests/peers/pymodbus_device.py), in
alternating rounds, so a noisy machine hurts both alike.  mbtool runs as the
real command, writing JSON lines to a pipe; its rate is taken from the poll
time stamps, so Python's start-up is not counted against it.

Run by hand:  python bench/polling.py [--polls 2000] [--rounds 3]
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import re
import select
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import time
import tty
from datetime import datetime
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
DEVICE = ROOT / "tests" / "peers" / "pymodbus_device.py"
COUNT = 10  # holding registers per read


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


# With two cores or more, the device gets one and the client under test another: the
# figures then do not depend on where the scheduler happens to put three busy processes.
PINNED = len(os.sched_getaffinity(0)) >= 2
DEVICE_CORE, CLIENT_CORE = {0}, {1}


def on_core(cores: set[int]):
    return (lambda: os.sched_setaffinity(0, cores)) if PINNED else None


@contextlib.contextmanager
def device(*where: str):
    proc = subprocess.Popen(
        [sys.executable, str(DEVICE), *where, "--units", "1"],
        stdout=subprocess.PIPE,
        text=True,
        preexec_fn=on_core(DEVICE_CORE),
    )
    try:
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline:
            if proc.stdout.readline().strip() == "READY":
                break
        else:
            sys.exit("bench: the pymodbus device did not start")
        yield proc
    finally:
        proc.terminate()
        proc.wait(timeout=5)


class PtyCable:
    """Two pty pairs joined by a relay process: a serial cable with no baud rate.

    A process of its own on the device's core, so the relay neither takes the client's
    core nor shares a GIL with pymodbus's client in this process.
    """

    def __init__(self) -> None:
        self.fds = [os.openpty(), os.openpty()]
        for master, slave in self.fds:
            tty.setraw(master)
            tty.setraw(slave)
        self.device_path, self.master_path = (os.ttyname(slave) for _, slave in self.fds)
        self.relay = os.fork()
        if self.relay == 0:
            if PINNED:
                os.sched_setaffinity(0, DEVICE_CORE)
            self._relay()

    def _relay(self) -> None:
        a, b = self.fds[0][0], self.fds[1][0]
        other = {a: b, b: a}
        try:
            while True:
                for fd in select.select([a, b], [], [])[0]:
                    os.write(other[fd], os.read(fd, 4096))
        finally:
            os._exit(0)

    def close(self) -> None:
        os.kill(self.relay, signal.SIGTERM)
        os.waitpid(self.relay, 0)
        for pair in self.fds:
            for fd in pair:
                os.close(fd)


def mbtool_rate(target: str, polls: int, *options: str) -> float:
    """Transactions per second of mbtool's polling loop, from its poll time stamps.

    Its JSON lines go to a file, as from cron (``>> log``): a pipe read by this script
    would add a third process to wake on every poll of a two-core machine.
    """
    command = [sys.executable, "-m", "mbtool", "read-holding-registers", "0", str(COUNT), "-p", target]
    command += ["--interval", "0", "--polls", str(polls), "-o", "json", *options]
    with tempfile.TemporaryFile("w+") as log:
        result = subprocess.run(
            command,
            stdout=log,
            stderr=subprocess.PIPE,
            text=True,
            cwd=ROOT,
            timeout=600,
            preexec_fn=on_core(CLIENT_CORE),
        )
        log.seek(0)
        lines = [json.loads(line) for line in log]
    failed = [line for line in lines if "error" in line]
    if result.returncode != 0 or failed or len(lines) != polls:
        sys.exit(f"bench: mbtool failed ({result.returncode}): {result.stderr.strip()}")
    # Sustained: from the poll a tenth of the way in, as pymodbus's loop runs warm in this
    # process; a fresh process's first polls also pay for first-time code paths.
    warm = polls // 10
    first, last = (datetime.fromisoformat(lines[i]["time"]) for i in (warm, -1))
    # The summary's average latency: from a request sent to its reply, the device's share.
    ROUND_TRIPS.append(float(re.search(r"min/avg/max [\d.]+/([\d.]+)/", result.stderr).group(1)) / 1000)
    return (polls - 1 - warm) / (last - first).total_seconds()


ROUND_TRIPS: list[float] = []  # seconds, one a mbtool run


def pymodbus_rate(client, polls: int) -> float:
    client.read_holding_registers(0, count=COUNT, device_id=1)  # connected and warm, as mbtool is
    start = time.perf_counter()
    for _ in range(polls):
        reply = client.read_holding_registers(0, count=COUNT, device_id=1)
        if reply.isError() or len(reply.registers) != COUNT:
            sys.exit(f"bench: pymodbus read failed: {reply}")
    return polls / (time.perf_counter() - start)


def side_by_side(title: str, mbtool_run, pymodbus_run, rounds: int) -> tuple[float, float]:
    ours, theirs = [], []
    for round_ in range(rounds):
        # Each goes first in every other round: whatever the one before leaves behind
        # (caches, a process's exit) falls on both alike.
        if round_ % 2:
            theirs.append(pymodbus_run())
            ours.append(mbtool_run())
        else:
            ours.append(mbtool_run())
            theirs.append(pymodbus_run())
    mb, pm = statistics.median(ours), statistics.median(theirs)
    print(f"{title}")
    print(f"  mbtool    {mb:8.0f} transactions/s  ({1000 / mb:.3f} ms each)  rounds: {fmt(ours)}")
    print(f"  pymodbus  {pm:8.0f} transactions/s  ({1000 / pm:.3f} ms each)  rounds: {fmt(theirs)}")
    ahead = sum(o > t for o, t in zip(ours, theirs, strict=True))
    print(f"  mbtool / pymodbus: {mb / pm:.2f}  (mbtool ahead in {ahead} of {rounds} rounds)")
    return mb, pm


def fmt(rates: list[float]) -> str:
    return " ".join(f"{r:.0f}" for r in rates)


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--polls", type=int, default=2000, help="reads per round (default 2000)")
    parser.add_argument("--rounds", type=int, default=3, help="alternating rounds per peer (default 3)")
    parser.add_argument("--baud", type=int, default=115200, help="baud rate mbtool assumes on the pty")
    args = parser.parse_args()

    from pymodbus import FramerType
    from pymodbus.client import ModbusSerialClient, ModbusTcpClient

    if PINNED:
        os.sched_setaffinity(0, CLIENT_CORE)  # pymodbus's client runs in this process
        print(f"device on core {min(DEVICE_CORE)}, clients on core {min(CLIENT_CORE)}")

    port = free_port()
    with device("--tcp", f"127.0.0.1:{port}", "--framer", "socket"):
        client = ModbusTcpClient("127.0.0.1", port=port, timeout=2)
        client.connect()
        side_by_side(
            f"TCP loopback, FC03 x {COUNT} registers, {args.polls} polls a round",
            lambda: mbtool_rate(f"tcp://127.0.0.1:{port}", args.polls),
            lambda: pymodbus_rate(client, args.polls),
            args.rounds,
        )
        client.close()

    ROUND_TRIPS.clear()
    cable = PtyCable()
    try:
        with device("--serial", cable.device_path, "--framer", "rtu"):
            client = ModbusSerialClient(
                cable.master_path, framer=FramerType.RTU, baudrate=args.baud, timeout=2
            )
            client.connect()
            polls = max(args.polls // 4, 50)
            mb, _ = side_by_side(
                f"RTU over a pseudo-terminal at a nominal {args.baud} baud, {polls} polls a round",
                lambda: mbtool_rate(cable.master_path, polls, "-b", str(args.baud), "--parity", "N"),
                lambda: pymodbus_rate(client, polls),
                args.rounds,
            )
            client.close()
    finally:
        cable.close()
    # spec §2: t3.5 is 3.5 characters of 11 bits, fixed at 1.75 ms above 19200 baud
    t35 = 0.00175 if args.baud > 19200 else 3.5 * 11 / args.baud
    each, answer = 1 / mb, statistics.median(ROUND_TRIPS)
    print(
        f"  mbtool on the pty: {each * 1000:.3f} ms a transaction = t3.5 {t35 * 1000:.3f} ms"
        f" + request to reply {answer * 1000:.3f} ms (the device's turnaround; a pty has no wire"
        f" time) + {(each - t35 - answer) * 1000:.3f} ms mbtool's own overhead"
    )


if __name__ == "__main__":
    main()
