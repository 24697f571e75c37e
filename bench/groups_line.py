#!/usr/bin/env python3
"""Poll groups on a paced 9600-baud serial line (issue 44, its first "done when").

A device with a fast group of 4 holding registers every second and a slow group of 100
every minute, polled by ``mbtool poll`` on the line's master end, ``mbtool serve`` answering
on its slave end.  It reports:

* the fast group's intervals: mean, min, max and the share within 1 s +- 10 % (target: all);
* the slow group's polls and the points each read;
* the line's load measured, from the emulator's byte counts (10 bits a character, 8N1) and
  its frames (each followed by t3.5 of silence), over the run, beside the budget check's
  estimate (``mbtool inventory check``; target: within 15 %);
* the same plant the old way, one interval for everything (every second), its polls' intervals
  and its load, for comparison.

``--devices N`` puts N such devices (units 1..N) on the line: the old way asks a quarter of the
line a device, so from 4 devices on it cannot keep its second, where the groups ask 3.3 % a device.

The line is an emulator that carries each character no sooner than the baud rate allows, both
directions sharing it (RS-485), between two pseudo-terminals.  It is not part of mbtool: give
its path with --wire (it takes ``BAUD BITS_PER_CHAR MASTER_LINK SLAVE_LINK [STATS_FILE]`` and
writes JSON statistics, its bytes and frames each way, on SIGTERM).

Run by hand:  python bench/groups_line.py --wire PATH/TO/wire.py [--seconds 300] [--devices 1]
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from plant import mbtool, serving, stamp
from serial_line import BITS, line

from mbtool.plant.budget import budgets
from mbtool.plant.inventory import load_inventory

ROOT = Path(__file__).resolve().parent.parent
BAUD = 9600
FAST, SLOW = 1.0, 60.0
MAP = "".join(f"[points.fast{n}]\nref = {40001 + n}\n" for n in range(4)) + "".join(
    f"[points.slow{n}]\nref = {40101 + n}\n" for n in range(100)
)
FAST_POINTS = ", ".join(f'"fast{n}"' for n in range(4))
SLOW_POINTS = ", ".join(f'"slow{n}"' for n in range(100))


def inventory(folder: Path, master: str, grouped: bool, devices: int) -> Path:
    (folder / "meter.toml").write_text(MAP)
    path = folder / ("groups.toml" if grouped else "single.toml")
    text = f'[poll]\ninterval = {FAST}\n[links.bus1]\ntarget = "{master}"\nbaud = {BAUD}\nparity = "N"\n'
    text += "timeout = 1\n"  # a 100-register reply takes 0.23 s; the machine may be busy
    for unit in range(1, devices + 1):
        text += f'[devices.meter{unit}]\nlink = "bus1"\nunit = {unit}\nmap = "meter.toml"\n'
        if grouped:
            text += f"[devices.meter{unit}.groups.fast]\ninterval = {FAST}\npoints = [{FAST_POINTS}]\n"
            text += f"[devices.meter{unit}.groups.slow]\ninterval = {SLOW}\npoints = [{SLOW_POINTS}]\n"
    path.write_text(text)
    return path


def estimate(plant: Path) -> float:
    """The budget check's load of the link (a fraction of the line), as inventory check prints
    it and to the digit."""
    out = subprocess.run(
        mbtool("inventory", "check", str(plant)), cwd=ROOT, capture_output=True, text=True, timeout=60
    )
    if out.returncode != 0:
        sys.exit(f"bench: inventory check: {out.stdout}{out.stderr}")
    print("  " + next(text for text in out.stdout.splitlines() if "budget:" in text).strip())
    loaded = load_inventory(str(plant))
    (budget,) = budgets(loaded.links, loaded.devices)
    return budget.seconds


def run(
    wire: str, folder: Path, seconds: float, grouped: bool, devices: int
) -> tuple[list[dict], float, dict]:
    """poll's records, the budget check's estimate and the line's statistics."""
    stats: list[dict] = []
    with line(wire, BAUD, folder, stats) as (master, slave), serving(slave, f"1-{devices}", BAUD):
        plant = inventory(folder, master, grouped, devices)
        asked = estimate(plant)
        done = subprocess.run(
            mbtool("poll", str(plant), "-o", "json", "--duration", str(seconds), "--stats", "json"),
            cwd=ROOT,
            capture_output=True,
            text=True,
            timeout=seconds + 60,
        )
    records = [json.loads(text) for text in done.stdout.splitlines()]
    if not records:
        sys.exit(f"bench: mbtool poll exited {done.returncode}: {done.stderr[-2000:]}")
    failed = [r for r in records if "error" in r]
    if failed:  # said, and the run still measured: a poll that failed is the line's time too
        print(
            f"  {len(failed)} failed polls (poll's exit status {done.returncode}): {[(r['time'], r['error']) for r in failed[:5]]}"
        )
    for event in (r for r in records if "event" in r):
        print(
            f"  event: {event.get('event')} {event.get('link', event.get('device'))}: {event.get('reason', '')}"
        )
    if not stats:
        sys.exit("bench: the line wrote no statistics")
    return [r for r in records if "event" not in r], asked, stats[0]


def intervals(records: list[dict]) -> list[float]:
    """The intervals between each device's successive polls among ``records``, every device's."""
    gaps = []
    for device in sorted({r["device"] for r in records}):
        times = [stamp(r) for r in records if r["device"] == device]
        gaps += [b - a for a, b in zip(times, times[1:], strict=False)]
    return gaps


def show_intervals(name: str, gaps: list[float], asked: float) -> None:
    within = sum(abs(gap - asked) <= 0.1 * asked for gap in gaps)
    print(
        f"  {name}: {len(gaps)} intervals, mean {statistics.mean(gaps):.3f} s, "
        f"min {min(gaps):.3f}, max {max(gaps):.3f}; within {asked:g} s +-10%: {within} of {len(gaps)} "
        f"({within / len(gaps):.1%})"
    )


def measured_load(stats: dict, records: list[dict]) -> float:
    """The line's busy share over the polls: every character's bits and each frame's t3.5
    after it, over the time from the first poll to a second after the last one's start."""
    char = BITS / BAUD
    t35 = 3.5 * char
    characters = stats["bytes"]["master"] + stats["bytes"]["slave"]
    frames = stats["frames"]["master"] + stats["frames"]["slave"]
    span = stamp(records[-1]) - stamp(records[0]) + FAST
    print(
        f"  line: {characters} characters, {frames} frames in {span:.1f} s; t3.5 violations {stats.get('t35_violations')}"
    )
    return (characters * char + frames * t35) / span


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--wire", required=True, help="the paced-line emulator (wire.py)")
    parser.add_argument("--seconds", type=float, default=300.0, help="each run's length (default 300)")
    parser.add_argument("--devices", type=int, default=1, help="such devices on the line (default 1)")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="mbtool-groups-") as where:
        folder = Path(where)
        print(
            f"groups: {args.devices} device(s), each fast {FAST:g} s (4 registers) and slow {SLOW:g} s "
            f"(100 registers), {BAUD} baud 8N1, {args.seconds:g} s"
        )
        records, grouped, stats = run(args.wire, folder, args.seconds, True, args.devices)
        show_intervals("fast group", intervals([r for r in records if r.get("group") == "fast"]), FAST)
        slow = [r for r in records if r.get("group") == "slow"]
        print(f"  slow group: {len(slow)} polls of {sorted({len(r['points']) for r in slow})} points")
        load = measured_load(stats, records)
        print(
            f"  load measured {load:.4f} of the line ({load:.2%}), estimated {grouped:.4f}: "
            f"the estimate is {grouped / load - 1:+.1%} of the measure"
        )
        print(f"single interval (the old way): every point every {FAST:g} s")
        records, single, stats = run(args.wire, folder, args.seconds, False, args.devices)
        show_intervals("every point", intervals(records), FAST)
        load = measured_load(stats, records)
        print(
            f"  load measured {load:.4f} of the line ({load:.2%}), estimated {single:.4f}: "
            f"the estimate is {single / load - 1:+.1%} of the measure"
        )
        print(
            f"  such devices the line carries at their pace: {1 / single:.1f} the old way, {1 / grouped:.1f} with groups"
        )


if __name__ == "__main__":
    main()
