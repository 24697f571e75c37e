#!/usr/bin/env python3
"""Polling on a paced serial line: mbtool beside pymodbus and libmodbus, and what
``mbtool bridge`` adds to a transaction beyond the line's own time.

Targets:

* issue 19 (fast where it counts): on a 9600-baud line mbtool keeps 0 t3.5 violations and
  makes at least 1.1 x pymodbus's transactions a second;
* issue 18 (a gateway): the bridge adds less than 1 ms per transaction.

The line is an emulator that carries each character no sooner than the baud rate allows,
both directions sharing it (RS-485), between two pseudo-terminals; it counts the master's
t3.5 violations.  It is not part of mbtool: give its path with --wire (the one this was
written against takes ``BAUD BITS_PER_CHAR MASTER_LINK SLAVE_LINK [STATS_FILE]`` and writes
JSON statistics on SIGTERM).  The line is 8N1, so a character is 10 bits.

On the line's slave end ``mbtool serve`` answers reads of 10 holding registers, t3.5
after each request.  Each master reads them back to back, a fresh line a run, in
alternating rounds: directly on the line's master end mbtool's polling loop, pymodbus's
serial client and libmodbus's C client (built with gcc against Debian's libmodbus-dev;
left out, saying why, where it cannot be); through ``mbtool bridge`` on the line's master
end, over Modbus TCP on loopback, mbtool's polling loop and pymodbus's TCP client.

Run by hand:  python bench/serial_line.py --wire PATH/TO/wire.py [--baud 9600] [--polls 150]
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
from datetime import datetime
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
COUNT = 10  # holding registers per read
BITS = 10  # a character of 8N1: start, 8 data, stop


@contextlib.contextmanager
def line(wire: str, baud: int, where: Path, results: list[dict]):
    """The emulated line; its statistics go to ``results`` when it stops."""
    master, slave, stats = where / "master", where / "slave", where / "stats.json"
    proc = subprocess.Popen([sys.executable, wire, str(baud), str(BITS), str(master), str(slave), str(stats)])
    try:
        deadline = time.monotonic() + 10
        while not (master.exists() and slave.exists()):
            if time.monotonic() > deadline or proc.poll() is not None:
                sys.exit(f"bench: {wire} did not make its line")
            time.sleep(0.02)
        yield str(master), str(slave)
    finally:
        proc.terminate()
        proc.wait(timeout=10)
        if stats.exists():
            results.append(json.loads(stats.read_text()))
            stats.unlink()


@contextlib.contextmanager
def started(argv: list[str], ready: str, stream: str = "stdout"):
    """A subprocess, once it has printed a line starting with ``ready``; that line."""
    proc = subprocess.Popen(
        argv,
        cwd=ROOT,
        stdout=subprocess.PIPE if stream == "stdout" else subprocess.DEVNULL,
        stderr=subprocess.PIPE if stream == "stderr" else subprocess.DEVNULL,
        text=True,
    )
    pipe = proc.stdout if stream == "stdout" else proc.stderr
    try:
        first = pipe.readline()
        if not first.startswith(ready):
            sys.exit(f"bench: {' '.join(argv[2:4])} did not start: {first!r}")
        yield first
    finally:
        proc.terminate()
        proc.wait(timeout=15)


def libmodbus_client(workdir: Path) -> Path | None:
    """libmodbus's RTU client, or None (said why) where gcc or libmodbus-dev is missing."""
    from polling_cpu import CLIENT_C, build  # beside this script

    source = CLIENT_C.replace("NEW_CONTEXT", "modbus_new_rtu(argv[1], atoi(argv[2]), 'N', 8, 1)")
    try:
        return build(workdir, {"rtu_client": source})[0]
    except SystemExit as why:
        print(f"{why}: libmodbus left out")
        return None


def mbtool(*args: str) -> list[str]:
    return [sys.executable, "-m", "mbtool", *args]


def serial(baud: int) -> list[str]:
    return ["-b", str(baud), "--parity", "N"]


def mbtool_seconds(target: str, polls: int, *options: str) -> float:
    """Seconds a transaction of mbtool's polling loop, from its poll time stamps; its
    summary's mean latency (request sent to reply) goes to LATENCIES."""
    command = mbtool("read-holding-registers", "0", str(COUNT), "-p", target, "--interval", "0")
    command += ["--polls", str(polls), "-o", "json", *options]
    with tempfile.TemporaryFile("w+") as log:
        done = subprocess.run(command, stdout=log, stderr=subprocess.PIPE, text=True, cwd=ROOT, timeout=600)
        log.seek(0)
        lines = [json.loads(text) for text in log]
    if done.returncode != 0 or len(lines) != polls or any("error" in entry for entry in lines):
        sys.exit(f"bench: mbtool failed ({done.returncode}): {done.stderr.strip()}")
    first, last = (datetime.fromisoformat(lines[i]["time"]) for i in (1, -1))
    LATENCIES.append(float(re.search(r"min/avg/max [\d.]+/([\d.]+)/", done.stderr).group(1)) / 1000)
    return (last - first).total_seconds() / (polls - 2)


LATENCIES: list[float] = []  # seconds, one a mbtool run


def pymodbus_seconds(client, polls: int) -> float:
    """Seconds a transaction of pymodbus's client reading in a loop; the client is
    connected here and closed after."""
    client.connect()
    try:
        client.read_holding_registers(0, count=COUNT, device_id=1)  # connected and warm
        start = time.perf_counter()
        for _ in range(polls):
            reply = client.read_holding_registers(0, count=COUNT, device_id=1)
            if reply.isError() or len(reply.registers) != COUNT:
                sys.exit(f"bench: pymodbus read failed: {reply}")
        return (time.perf_counter() - start) / polls
    finally:
        client.close()


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--wire", required=True, help="the paced-line emulator (wire.py)")
    parser.add_argument("--baud", type=int, default=9600, help="the line's baud rate (default 9600)")
    parser.add_argument("--polls", type=int, default=150, help="reads per run (default 150)")
    parser.add_argument("--rounds", type=int, default=2, help="rounds of the runs (default 2)")
    parser.add_argument(
        "--device",
        choices=["mbtool", "pymodbus"],
        default="mbtool",
        help="the device on the line: mbtool serve (answers t3.5 after a request), or pymodbus's "
        "RTU server (answers as soon as it can)",
    )
    args = parser.parse_args()

    from pymodbus.client import ModbusSerialClient, ModbusTcpClient

    baud, polls = args.baud, args.polls
    # The line's own time for one read: request (8 bytes) and reply (5 + 2 x COUNT bytes) at
    # BITS bits a character, and the two t3.5 silences of the same characters (spec §2).
    characters = 8 + 5 + 2 * COUNT
    line_time = (characters + 2 * 3.5) * BITS / baud
    names = ["mbtool", "pymodbus", "libmodbus", "mbtool via bridge", "pymodbus via bridge"]
    libmodbus = libmodbus_client(Path(tempfile.mkdtemp(prefix="mbtool-bench-")))
    if libmodbus is None:
        names.remove("libmodbus")
    runs: dict[str, list[float]] = {name: [] for name in names}
    stats: dict[str, list[dict]] = {name: [] for name in runs}

    latencies: dict[str, list[float]] = {"mbtool": [], "mbtool via bridge": []}

    def on_line(name: str, measure) -> None:
        with tempfile.TemporaryDirectory(prefix="mbtool-bench-") as where:
            with line(args.wire, baud, Path(where), stats[name]) as (master, slave):
                if args.device == "pymodbus":
                    device = [sys.executable, str(ROOT / "tests/peers/pymodbus_device.py"), "--serial", slave]
                    device += ["--baud", str(baud), "--units", "1"]
                    ready = "READY"
                else:
                    device, ready = mbtool("serve", "-p", slave, "-u", "1", "-q", *serial(baud)), "serving "
                with started(device, ready):
                    runs[name].append(measure(master))
        if name in latencies:
            latencies[name].append(LATENCIES[-1])

    def via_bridge(master: str, measure_tcp) -> float:
        command = mbtool("bridge", "--listen", "tcp://127.0.0.1:0", "-p", master, "-q", *serial(baud))
        with started(command, "bridging ", stream="stderr") as first:
            return measure_tcp(first.split()[1])

    def pymodbus_direct(master: str) -> float:
        client = ModbusSerialClient(master, baudrate=baud, parity="N", timeout=2, retries=0)
        return pymodbus_seconds(client, polls)

    def pymodbus_tcp(target: str) -> float:
        host, _, port = target.removeprefix("tcp://").rpartition(":")
        return pymodbus_seconds(ModbusTcpClient(host, port=int(port), timeout=2, retries=0), polls)

    def libmodbus_direct(master: str) -> float:
        began = time.perf_counter()
        done = subprocess.run([str(libmodbus), master, str(baud), str(polls)], capture_output=True, text=True)
        if done.returncode:
            sys.exit(f"bench: libmodbus's client failed: {done.stderr.strip()}")
        return (time.perf_counter() - began) / polls

    measures = {
        "mbtool": lambda master: mbtool_seconds(master, polls, *serial(baud)),
        "pymodbus": pymodbus_direct,
        "libmodbus": libmodbus_direct,
        "mbtool via bridge": lambda master: via_bridge(master, lambda tcp: mbtool_seconds(tcp, polls)),
        "pymodbus via bridge": lambda master: via_bridge(master, pymodbus_tcp),
    }
    plan = [(name, measures[name]) for name in names]
    for round_ in range(args.rounds):
        for name, measure in plan if round_ % 2 == 0 else plan[::-1]:
            on_line(name, measure)

    print(
        f"FC03 x {COUNT} registers on an emulated {baud}-baud line, {polls} reads a run, {args.rounds} rounds,"
        f" {args.device} as the device"
    )
    print(f"  the line's own time: {line_time * 1000:.2f} ms a read ({characters} characters and two t3.5)")
    median = {name: statistics.median(values) for name, values in runs.items()}
    for name, values in runs.items():
        violations = sum(s["t35_violations"] for s in stats[name])
        frames = sum(s["frames"]["master"] for s in stats[name])
        print(
            f"  {name:20} {median[name] * 1000:7.2f} ms a read ({1 / median[name]:5.1f} tx/s)"
            f"  runs: {' '.join(f'{v * 1000:.2f}' for v in values)}"
            f"  t3.5 violations: {violations} in {frames} frames"
        )
    print(
        f"  mbtool / pymodbus: {median['pymodbus'] / median['mbtool']:.2f} x the transactions a second (target >= 1.1)"
    )
    for master in ("mbtool", "pymodbus"):
        added = median[f"{master} via bridge"] - median[master]
        print(f"  the bridge adds {added * 1000:+.2f} ms a transaction ({master} as the TCP client)")
    # Latency: a TCP client's next request comes at once, and the bridge keeps the line
    # silent for t3.5 before passing it on; on the line the master waits that out before
    # its clock starts.  What is left beyond that silence is the bridge's own.
    direct, bridged = (statistics.median(latencies[name]) for name in ("mbtool", "mbtool via bridge"))
    t35 = 3.5 * BITS / baud
    print(
        f"  mbtool's latency, request to reply: on the line {direct * 1000:.2f} ms, via the bridge "
        f"{bridged * 1000:.2f} ms = the line's + t3.5 {t35 * 1000:.2f} ms + {(bridged - direct - t35) * 1000:+.2f} ms"
    )
    # The ceiling: request to reply is the line's and the device's time, the same for every
    # master; after the reply the line must stay silent t3.5 (spec §2).  No master that keeps
    # t3.5 reads faster than their sum, which bounds the ratio to pymodbus on this line.
    fastest = direct + t35
    print(
        f"  the fastest a master keeping t3.5 can read here: {fastest * 1000:.2f} ms"
        f" = {median['pymodbus'] / fastest:.3f} x pymodbus; mbtool's own time beyond it"
        f" {(median['mbtool'] - fastest) * 1000:+.2f} ms a read"
    )


if __name__ == "__main__":
    os.environ.setdefault("PYTHONDONTWRITEBYTECODE", "1")
    main()
