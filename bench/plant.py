#!/usr/bin/env python3
"""``mbtool poll``: a plant's rounds beside the line's own time, a dead unit, buses in
parallel, and 50 TCP devices for minutes (issue 31's benchmarks).

Targets, each measured against its reference in the same run:

* **line**: one bus on an emulated 9600-baud line, 8 units, a read of 10 registers each:
  a round takes at most 1.05 x the line's own time for those frames: each request's and
  reply's characters, and the t3.5 of silence after each (the device's turnaround and the
  master's wait before the next request);
* **dead**: the same with one unit dead: once it is offline, a round takes at most 1.1 x
  the round of the 7 live units polled alone;
* **parallel**: four such buses at once: a round takes at most 1.1 x the slowest bus alone;
* **tcp**: 50 TCP devices (one port each, one server listening on all 50) polled every
  0.1 s for minutes: every device polled in every round, CPU per transaction at most
  1.5 x that of one device polled the same way, RSS growth under 5 MB.

The line is an emulator that carries each character no sooner than the baud rate allows,
both directions sharing it, between two pseudo-terminals (the one bench/serial_line.py
uses: give its path with --wire).  ``mbtool serve`` answers on the line's slave end, t3.5
after each request.  A round is measured from the JSON records poll writes: the time
between one device's successive polls, averaged over the run.

Run by hand:  python bench/plant.py --wire PATH/TO/wire.py [--only line,dead,parallel,tcp]
              [--rounds 30] [--dead-seconds 40] [--tcp-seconds 300]
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import struct
import subprocess
import sys
import tempfile
import threading
import time
from datetime import datetime
from pathlib import Path

from serial_line import BITS, COUNT, line

ROOT = Path(__file__).resolve().parent.parent
UNITS = 8


def mbtool(*args: str) -> list[str]:
    return [sys.executable, "-m", "mbtool", *args]


@contextlib.contextmanager
def serving(where: str, units: str, baud: int):
    proc = subprocess.Popen(
        mbtool("serve", "-p", where, "-u", units, "--framer", "rtu", "--parity", "N", "-b", str(baud), "-q"),
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
    )
    try:
        if not proc.stdout.readline().startswith("serving"):
            sys.exit("bench: mbtool serve did not start")
        yield
    finally:
        proc.terminate()
        proc.wait(timeout=10)


def inventory(
    folder: Path, buses: dict[str, str], units: dict[str, list[int]], baud: int, interval: float
) -> Path:
    text = f"[poll]\ninterval = {interval}\n"
    for name, target in buses.items():
        text += f'[links.{name}]\ntarget = "{target}"\nbaud = {baud}\nparity = "N"\ntimeout = 0.2\n'
        for unit in units[name]:
            text += f'[devices.{name}_u{unit}]\nlink = "{name}"\nunit = {unit}\nread = ["40001 {COUNT}"]\n'
    path = folder / "plant.toml"
    path.write_text(text)
    return path


def run_poll(plant: Path, *args: str) -> tuple[list[dict], float]:
    """poll's records, and its CPU seconds (user + system)."""
    before = os.times()
    done = subprocess.run(
        mbtool("poll", str(plant), "-o", "json", "--stats", "json", *args),
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=3600,
    )
    after = os.times()
    if done.returncode not in (0, 8):
        sys.exit(f"bench: mbtool poll exited {done.returncode}: {done.stderr[-2000:]}")
    cpu = (after.children_user - before.children_user) + (after.children_system - before.children_system)
    return [json.loads(row) for row in done.stdout.splitlines()], cpu


def stamp(record: dict) -> float:
    return datetime.fromisoformat(record["time"]).timestamp()


def round_seconds(records: list[dict], device: str, after: float = 0.0) -> float:
    """The mean time between a device's successive polls (from ``after`` on)."""
    times = [
        stamp(r) for r in records if r.get("device") == device and "event" not in r and stamp(r) >= after
    ]
    if len(times) < 3:
        sys.exit(f"bench: {device} was polled {len(times)} times")
    return (times[-1] - times[0]) / (len(times) - 1)


def line_round(baud: int, units: int) -> float:
    """The line's own time for a round: each request (8 characters) and reply (5 + 2 a
    register), each followed by t3.5 of silence (spec §2: 3.5 characters at 9600 baud)."""
    char = BITS / baud
    t35 = 0.00175 if baud > 19200 else 3.5 * char
    return units * ((8 + 5 + 2 * COUNT) * char + 2 * t35)


def one_bus(
    wire: str, baud: int, units: list[int], rounds: int, folder: Path, *args: str
) -> tuple[float, dict]:
    stats: list[dict] = []
    with line(wire, baud, folder, stats) as (master, slave), serving(slave, "1-8", baud):
        plant = inventory(folder, {"bus": master}, {"bus": units}, baud, 0.01)
        records, _ = run_poll(plant, "--rounds", str(rounds), *args)
    return round_seconds(records, f"bus_u{units[0]}"), (stats[0] if stats else {})


def transaction_on_the_line(master: str, baud: int, polls: int) -> float:
    """Seconds a transaction takes on the line, measured: mbtool's one-device polling loop
    reading the same 10 registers back to back (bench/serial_line.py shows it within 0.5%
    of the line's characters, the device's turnaround and t3.5)."""
    done = subprocess.run(
        mbtool("read-holding-registers", "0", str(COUNT), "-p", master, "--parity", "N", "-b", str(baud),
               "--interval", "0", "--polls", str(polls), "-t", "0.2", "-o", "plain"),
        cwd=ROOT, capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    rate = done.stderr.strip().splitlines()[-1].split("; ", 1)[0].rsplit(", ", 1)[-1]  # "23 polls/s"
    if done.returncode or not rate.endswith("polls/s"):
        sys.exit(f"bench: the polling loop failed: {done.stderr[-500:]}")
    return 1 / float(rate.split()[0])


def bench_line(args, folder: Path) -> None:
    stats: list[dict] = []
    with line(args.wire, args.baud, folder, stats) as (master, slave), serving(slave, "1-8", args.baud):
        plant = inventory(folder, {"bus": master}, {"bus": list(range(1, UNITS + 1))}, args.baud, 0.01)
        records, _ = run_poll(plant, "--rounds", str(args.rounds))
        transaction = transaction_on_the_line(master, args.baud, UNITS * args.rounds)
    measured = round_seconds(records, "bus_u1")
    ceiling = line_round(args.baud, UNITS)
    print(
        f"line: 8 units at {args.baud} baud: a round {measured * 1000:.1f} ms; the line's own time for those "
        f"frames {ceiling * 1000:.1f} ms (characters, and t3.5 after each frame): {measured / ceiling:.3f} x "
        f"(target <= 1.05); beside 8 transactions of the one-device polling loop on the same line "
        f"({UNITS * transaction * 1000:.1f} ms): {measured / (UNITS * transaction):.3f} x; "
        f"t3.5 violations {stats[0].get('t35_violations', '?') if stats else '?'}"
    )


def bench_dead(args, folder: Path) -> None:
    """7 live units and a dead one, the dead one offline: rounds measured after it went
    offline, beside the 7 live units polled alone, for the same time."""
    results = {}
    for name, units in (("7 live", list(range(1, UNITS))), ("7 live + 1 dead", list(range(1, UNITS)) + [9])):
        stats: list[dict] = []
        with line(args.wire, args.baud, folder, stats) as (master, slave), serving(slave, "1-7", args.baud):
            plant = inventory(folder, {"bus": master}, {"bus": units}, args.baud, 0.3)
            records, _ = run_poll(plant, "--duration", str(args.dead_seconds))
        offline = [stamp(r) for r in records if r.get("event") == "offline"]
        if units[-1] == 9 and not offline:
            sys.exit("bench: the dead unit never went offline")
        results[name] = round_seconds(records, "bus_u1", after=offline[0] if offline else 0.0)
        probes = sum(1 for r in records if r.get("device") == "bus_u9" and "event" not in r)
        print(
            f"dead: {name}: a round {results[name] * 1000:.1f} ms"
            + (f" ({probes} polls of the dead unit)" if units[-1] == 9 else "")
        )
    ratio = results["7 live + 1 dead"] / results["7 live"]
    print(f"dead: {ratio:.3f} x the round of the 7 live units (target <= 1.1)")


def bench_parallel(args, folder: Path) -> None:
    alone = {}
    for index in range(4):
        where = folder / f"alone{index}"
        where.mkdir(exist_ok=True)
        alone[index], _ = one_bus(args.wire, args.baud, list(range(1, UNITS + 1)), args.rounds, where)
    with contextlib.ExitStack() as stack:
        buses = {}
        for index in range(4):
            where = folder / f"bus{index}"
            where.mkdir(exist_ok=True)
            master, slave = stack.enter_context(line(args.wire, args.baud, where, []))
            stack.enter_context(serving(slave, "1-8", args.baud))
            buses[f"bus{index}"] = master
        plant = inventory(folder, buses, {name: list(range(1, UNITS + 1)) for name in buses}, args.baud, 0.01)
        records, _ = run_poll(plant, "--rounds", str(args.rounds))
    together = {name: round_seconds(records, f"{name}_u1") for name in buses}
    slowest = max(alone.values())
    print(
        "parallel: each bus alone "
        + ", ".join(f"{s * 1000:.1f}" for s in alone.values())
        + " ms; four at once "
        + ", ".join(f"{s * 1000:.1f}" for s in together.values())
        + f" ms: {max(together.values()) / slowest:.3f} x the slowest alone (target <= 1.1)"
    )


# --- 50 TCP devices ---------------------------------------------------------------------------


def tcp_server(ports: list[int], ready: threading.Event, registers: int = COUNT) -> None:
    """One asyncio server on every port: FC 03 of ``registers`` registers answered at once,
    their values counted up with every reply (a meter's readings move: no reply is the one
    before, so no reply decoded or published before can stand for it)."""
    values = struct.Struct(f">{registers}H")
    head = bytes([3, 2 * registers])
    offsets = range(registers)

    async def client(reader, writer):
        count = 0
        try:
            while True:
                request = await reader.readexactly(7)
                tid, _, length, unit = struct.unpack(">HHHB", request)
                await reader.readexactly(length - 1)
                count = (count + 1) & 0x7FFF
                reply = head + values.pack(*(count + i for i in offsets))
                writer.write(struct.pack(">HHHB", tid, 0, len(reply) + 1, unit) + reply)
        except (asyncio.IncompleteReadError, ConnectionError):
            writer.close()

    async def main():
        servers = [await asyncio.start_server(client, "127.0.0.1", port) for port in ports]
        ready.set()
        await asyncio.gather(*(server.serve_forever() for server in servers))

    asyncio.run(main())


def tcp_inventory(ports: list[int], interval: float, registers: int) -> str:
    """A plant of a TCP device on each of ``ports`` (tcp_server's), each on a link of its own,
    polled every ``interval`` s for ``registers`` holding registers from 40001."""
    text = f"[poll]\ninterval = {interval}\n"
    for index, port in enumerate(ports):
        text += f'[links.l{index}]\ntarget = "tcp://127.0.0.1:{port}"\n'
        text += f'[devices.d{index}]\nlink = "l{index}"\nread = ["40001 {registers}"]\n'
    return text


def free_ports(count: int) -> list[int]:
    import socket

    sockets = [socket.socket() for _ in range(count)]
    for each in sockets:
        each.bind(("127.0.0.1", 0))
    ports = [each.getsockname()[1] for each in sockets]
    for each in sockets:
        each.close()
    return ports


def cpu_seconds(pid: int) -> float:
    """User and system CPU time the process has used so far (/proc/PID/stat)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def rss_kb(pid: int) -> int:
    for row in Path(f"/proc/{pid}/status").read_text().splitlines():
        if row.startswith("VmRSS:"):
            return int(row.split()[1])
    return 0


def bench_tcp(args, folder: Path) -> None:
    count, interval = 50, 0.1
    ports = free_ports(count)
    server = subprocess.Popen(
        [sys.executable, __file__, "--serve-tcp", ",".join(map(str, ports))],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        if server.stdout.readline().strip() != "ready":
            sys.exit("bench: the TCP server did not start")
        cpu_per_transaction = {}
        for devices in (1, count):
            plant = folder / f"tcp{devices}.toml"
            plant.write_text(tcp_inventory(ports[:devices], interval, COUNT))
            out = folder / f"tcp{devices}.jsonl"
            seconds = args.tcp_seconds
            with open(out, "w") as sink:
                proc = subprocess.Popen(
                    mbtool("poll", str(plant), "-o", "json", "--duration", str(seconds), "--stats", "json"),
                    cwd=ROOT,
                    stdout=sink,
                    stderr=subprocess.PIPE,
                    text=True,
                )
                # Steady state: from once every link is open to a second before the end, the
                # CPU the process used and the polls it made in between (start-up left out).
                time.sleep(min(10, seconds / 3))
                first = (time.time(), cpu_seconds(proc.pid), rss_kb(proc.pid))
                time.sleep(max(1, seconds - min(10, seconds / 3) - 2))
                last = (time.time(), cpu_seconds(proc.pid), rss_kb(proc.pid))
                err = proc.stderr.read()
                proc.wait()
            stats = json.loads(err.strip().splitlines()[-2])
            transactions = sum(device["transactions"] for device in stats["devices"].values())
            answered = sum(device["answered"] for device in stats["devices"].values())
            polls: dict[str, list[float]] = {}
            for row in out.read_text().splitlines():
                record = json.loads(row)
                polls.setdefault(record["device"], []).append(stamp(record))
            steady = sum(1 for times in polls.values() for t in times if first[0] <= t < last[0])
            cpu = last[1] - first[1]
            rss_start, rss_end = first[2], last[2]
            rounds = seconds / interval
            fewest = min(len(times) for times in polls.values())
            longest_gap = max(
                b - a for times in polls.values() for a, b in zip(times, times[1:], strict=False)
            )
            cpu_per_transaction[devices] = cpu / steady
            print(
                f"tcp: {devices} device(s) every {interval} s for {seconds:g} s: {transactions} transactions, "
                f"{answered} answered; polls a device min {fewest} of {rounds:.0f} slots, longest gap "
                f"{longest_gap * 1000:.0f} ms; steady state: CPU {cpu:.2f} s for {steady} transactions = "
                f"{cpu / steady * 1e6:.0f} us a transaction; "
                f"RSS {rss_start} -> {rss_end} kB (+{(rss_end - rss_start) / 1024:.1f} MB)"
            )
        ratio = cpu_per_transaction[count] / cpu_per_transaction[1]
        print(
            f"tcp: CPU a transaction, 50 devices / one device: {ratio:.2f} x (target <= 1.5); RSS growth target < 5 MB"
        )
    finally:
        server.terminate()
        server.wait(timeout=10)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--wire", help="the paced-line emulator (wire.py)")
    parser.add_argument("--baud", type=int, default=9600)
    parser.add_argument("--rounds", type=int, default=30)
    parser.add_argument("--dead-seconds", type=float, default=40)
    parser.add_argument("--tcp-seconds", type=float, default=300)
    parser.add_argument("--only", default="line,dead,parallel,tcp")
    parser.add_argument("--serve-tcp", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.serve_tcp:
        ready = threading.Event()
        thread = threading.Thread(
            target=tcp_server, args=([int(p) for p in args.serve_tcp.split(",")], ready)
        )
        thread.start()
        ready.wait(30)
        print("ready", flush=True)
        thread.join()
        return
    wanted = set(args.only.split(","))
    if wanted & {"line", "dead", "parallel"} and not args.wire:
        sys.exit("bench: give --wire PATH/TO/wire.py for the serial-line benchmarks")
    with tempfile.TemporaryDirectory(prefix="mbtool-plant-") as where:
        folder = Path(where)
        for name, bench in (
            ("line", bench_line),
            ("dead", bench_dead),
            ("parallel", bench_parallel),
            ("tcp", bench_tcp),
        ):
            if name in wanted:
                bench(args, folder)


if __name__ == "__main__":
    main()
