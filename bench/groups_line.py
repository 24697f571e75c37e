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

The line is an emulator that carries each character no sooner than the baud rate allows, both
directions sharing it (RS-485), between two pseudo-terminals.  It is not part of mbtool: give
its path with --wire (it takes ``BAUD BITS_PER_CHAR MASTER_LINK SLAVE_LINK [STATS_FILE]`` and
writes JSON statistics, its bytes and frames each way, on SIGTERM).

Run by hand:  python bench/groups_line.py --wire PATH/TO/wire.py [--seconds 300]
"""

from __future__ import annotations

import argparse
import json
import re
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from plant import mbtool, serving, stamp
from serial_line import BITS, line

ROOT = Path(__file__).resolve().parent.parent
BAUD = 9600
FAST, SLOW = 1.0, 60.0
MAP = "".join(f"[points.fast{n}]\nref = {40001 + n}\n" for n in range(4)) + "".join(
    f"[points.slow{n}]\nref = {40101 + n}\n" for n in range(100)
)
GROUPS = (
    f"[devices.meter.groups.fast]\ninterval = {FAST}\npoints = [{', '.join(f'{chr(34)}fast{n}{chr(34)}' for n in range(4))}]\n"
    f"[devices.meter.groups.slow]\ninterval = {SLOW}\npoints = [{', '.join(f'{chr(34)}slow{n}{chr(34)}' for n in range(100))}]\n"
)


def inventory(folder: Path, master: str, grouped: bool) -> Path:
    (folder / "meter.toml").write_text(MAP)
    path = folder / ("groups.toml" if grouped else "single.toml")
    path.write_text(
        f'[poll]\ninterval = {FAST}\n[links.bus1]\ntarget = "{master}"\nbaud = {BAUD}\nparity = "N"\n'
        'timeout = 0.5\n[devices.meter]\nlink = "bus1"\nunit = 1\nmap = "meter.toml"\n'
        + (GROUPS if grouped else "")
    )
    return path


def estimate(plant: Path) -> float:
    """The budget check's load of the link (a fraction of the line), from inventory check."""
    out = subprocess.run(
        mbtool("inventory", "check", str(plant)), cwd=ROOT, capture_output=True, text=True, timeout=60
    )
    found = re.search(r"budget: bus1: the asked polls need ([\d.]+) s ", out.stdout)
    if out.returncode != 0 or not found:
        sys.exit(f"bench: inventory check: {out.stdout}{out.stderr}")
    print("  " + next(text for text in out.stdout.splitlines() if "budget:" in text).strip())
    return float(found[1])


def run(wire: str, folder: Path, seconds: float, grouped: bool) -> tuple[list[dict], float, dict]:
    """poll's records, the run's seconds and the line's statistics."""
    stats: list[dict] = []
    with line(wire, BAUD, folder, stats) as (master, slave), serving(slave, "1", BAUD):
        plant = inventory(folder, master, grouped)
        asked = estimate(plant)
        done = subprocess.run(
            mbtool("poll", str(plant), "-o", "json", "--duration", str(seconds), "--stats", "json"),
            cwd=ROOT,
            capture_output=True,
            text=True,
            timeout=seconds + 60,
        )
    if done.returncode != 0:
        sys.exit(f"bench: mbtool poll exited {done.returncode}: {done.stderr[-2000:]}")
    records = [json.loads(text) for text in done.stdout.splitlines()]
    events = [r for r in records if "event" in r]
    for event in events:
        print(f"  event: {event}")
    if not stats:
        sys.exit("bench: the line wrote no statistics")
    return [r for r in records if "event" not in r], asked, stats[0]


def intervals(records: list[dict]) -> list[float]:
    times = [stamp(r) for r in records]
    return [b - a for a, b in zip(times, times[1:], strict=False)]


def show_intervals(name: str, gaps: list[float], asked: float) -> None:
    within = sum(abs(gap - asked) <= 0.1 * asked for gap in gaps)
    print(
        f"  {name}: {len(gaps) + 1} polls, interval mean {statistics.mean(gaps):.3f} s, "
        f"min {min(gaps):.3f}, max {max(gaps):.3f}; within {asked:g} s +-10%: {within} of {len(gaps)} "
        f"({within / len(gaps):.1%})"
    )


def measured_load(stats: dict, records: list[dict]) -> float:
    """The line's busy share over the polls: every character's bits and each frame's t3.5
    after it, over the time from the first poll to the last one's end (a poll's end: the next
    second's start, at most)."""
    char = BITS / BAUD
    t35 = 3.5 * char
    characters = stats["bytes"]["master"] + stats["bytes"]["slave"]
    frames = stats["frames"]["master"] + stats["frames"]["slave"]
    span = stamp(records[-1]) - stamp(records[0]) + FAST  # the last poll's second counted whole
    print(f"  line: {characters} characters, {frames} frames in {span:.1f} s")
    return (characters * char + frames * t35) / span


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--wire", required=True, help="the paced-line emulator (wire.py)")
    parser.add_argument("--seconds", type=float, default=300.0, help="each run's length (default 300)")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="mbtool-groups-") as where:
        folder = Path(where)
        print(
            f"groups: fast {FAST:g} s (4 registers), slow {SLOW:g} s (100 registers), {BAUD} baud 8N1, {args.seconds:g} s"
        )
        records, asked, stats = run(args.wire, folder, args.seconds, grouped=True)
        grouped = asked
        fast = [r for r in records if r.get("group") == "fast"]
        slow = [r for r in records if r.get("group") == "slow"]
        show_intervals("fast group", intervals(fast), FAST)
        print(f"  slow group: {len(slow)} polls, {[len(r['points']) for r in slow]} points each")
        load = measured_load(stats, records)
        print(
            f"  load measured {load:.4f} of the line ({load:.2%}), estimated {asked:.4f}: "
            f"the estimate is {asked / load - 1:+.1%} of the measure; t3.5 violations {stats.get('t35_violations')}"
        )
        print(f"single interval (the old way): everything every {FAST:g} s")
        records, asked, stats = run(args.wire, folder, args.seconds, grouped=False)
        show_intervals("every point", intervals(records), FAST)
        load = measured_load(stats, records)
        print(f"  load measured {load:.4f} of the line ({load:.2%}), estimated {asked:.4f}")
        print(
            f"  devices like this one the line carries at this pace: {1 / asked:.1f} (with groups: {1 / grouped:.1f})"
        )


if __name__ == "__main__":
    main()
