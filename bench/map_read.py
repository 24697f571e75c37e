#!/usr/bin/env python3
"""A register map of 200 points over the four tables, read whole, beside a one-shot read.

Target (issue: fast where it counts, "reads that scale"): the map is read in the fewest
requests the spec's limits (125 registers, 2000 bits a read) and the map's ``max_gap``
allow, and the whole read, process start to exit, over TCP costs at most 1.5 x a
one-shot read of 10 registers.

The map is made here, seeded: 50 points a table at scattered addresses, registers a mix
of uint16, int16 and float32.  The fewest requests are counted here too, growing each
read from the lowest address as far as the limit and ``max_gap`` let it (any plan's first
read ends no later than that one's, and so on), and compared with the requests mbtool
sends (its --hex trace).  ``mbtool serve`` is the device.

With ``--polls N`` the map is also polled (``--interval 0 --polls N -o json``), and the CPU
a poll costs is printed: user + system CPU (os.wait4's rusage) of a run of N polls less a
run of N/10, over the difference of polls, so start-up is taken out; the median of
``--rounds``.  Target (issue 30): a poll costs no more than it did.  ``--before DIR`` (an
earlier checkout, e.g. from ``git worktree add``) polls with that tree's mbtool too, in the
same run, the trees taking turns; ``--instructions`` counts a poll's instructions with
valgrind's callgrind as well (N/10 polls less N/100), which the machine's load does not move.

Run by hand:  python bench/map_read.py [-n 30] [--max-gap 4] [--seed 1]
                  [--polls 1000 [--rounds 3] [--before DIR] [--instructions]]
"""

from __future__ import annotations

import argparse
import os
import random
import re
import statistics
import subprocess
import sys
import sysconfig
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
# A tree's own mbtool, whatever is installed: its path first, then the command line.
LAUNCHER = "import sys; sys.path.insert(0, sys.argv.pop(1)); from mbtool.cli import main; sys.exit(main())"
TABLES = {  # reference prefix (Modicon), the spec's limit for one read
    "coils": (0, 2000),
    "discrete_inputs": (1, 2000),
    "input_registers": (3, 125),
    "holding_registers": (4, 125),
}
SIZES = {"uint16": 1, "int16": 1, "float32": 2}


def make_map(rng: random.Random, per_table: int, max_gap: int) -> tuple[str, int]:
    """The map's TOML and the fewest requests that read it."""
    lines = ["[device]", f"max_gap = {max_gap}", ""]
    fewest = 0
    for table, (prefix, limit) in TABLES.items():
        bits = prefix in (0, 1)
        spans = []  # (first, last) addresses of each point
        address = rng.randrange(50)
        for number in range(per_table):
            kind = "bool" if bits else rng.choice(list(SIZES))
            size = 1 if bits else SIZES[kind]
            spans.append((address, address + size - 1))
            lines.append(f"[points.{table}_{number}]")
            lines.append(f'ref = "{prefix}{address + 1:05d}"')  # six-digit references
            if not bits:
                lines.append(f'type = "{kind}"')
            lines.append("")
            # Mostly close together, now and then a long jump: some gaps merge, some do not.
            address += size + (rng.randrange(max_gap + 3) if rng.random() < 0.9 else rng.randrange(40, 400))
        fewest += fewest_reads(spans, limit, max_gap)
    return "\n".join(lines), fewest


def fewest_reads(spans: list[tuple[int, int]], limit: int, max_gap: int) -> int:
    reads, start, end = 0, None, None
    for first, last in sorted(spans):
        if start is not None and first - end - 1 <= max_gap and last - start + 1 <= limit:
            end = max(end, last)
            continue
        reads, start, end = reads + 1, first, last
    return reads


def timed(command: list[str]) -> float:
    began = time.perf_counter()
    done = subprocess.run(command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    if done.returncode:
        sys.exit(f"bench: {' '.join(command[1:3])} failed: {done.stderr.strip()}")
    return time.perf_counter() - began


def polling(tree: Path, map_file: Path, target: str, polls: int) -> list[str]:
    return [
        sys.executable,
        "-c",
        LAUNCHER,
        str(tree),
        "read",
        "-m",
        str(map_file),
        "-p",
        target,
        "--interval",
        "0",
        "--polls",
        str(polls),
        "-o",
        "json",
    ]


def cpu(command: list[str]) -> float:
    """User + system CPU seconds of one run of ``command``."""
    proc = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    _, status, usage = os.wait4(proc.pid, 0)
    if os.waitstatus_to_exitcode(status):
        sys.exit(f"bench: {' '.join(command[4:7])} failed: {proc.stderr.read().decode().strip()}")
    return usage.ru_utime + usage.ru_stime


def instructions(command: list[str]) -> int:
    """The instructions one run of ``command`` executes, as callgrind counts them."""
    with tempfile.TemporaryDirectory() as work:
        done = subprocess.run(
            ["valgrind", "--tool=callgrind", f"--callgrind-out-file={work}/out", *command],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
        )
    found = re.search(r"Collected : (\d+)", done.stderr)
    if done.returncode or found is None:
        sys.exit(f"bench: {' '.join(command[4:7])} failed under valgrind: {done.stderr[-2000:]}")
    return int(found.group(1))


def per_poll(measure, tree: Path, map_file: Path, target: str, short: int, long: int) -> float:
    """What one poll costs by ``measure``, start-up taken out: a long run less a short one."""
    low = measure(polling(tree, map_file, target, short))
    high = measure(polling(tree, map_file, target, long))
    return (high - low) / (long - short)


def polled(args, trees: list[Path], map_file: Path, target: str) -> list[str]:
    """The CPU (and with --instructions the instructions) a poll of the map costs, each
    tree's: the lines that say so."""
    seconds: dict[Path, list[float]] = {tree: [] for tree in trees}
    for round_number in range(args.rounds):
        for tree in trees if round_number % 2 == 0 else reversed(trees):  # turns: load hits all alike
            seconds[tree].append(per_poll(cpu, tree, map_file, target, args.polls // 10, args.polls))
    counted = {}
    if args.instructions:
        for tree in trees:
            counted[tree] = per_poll(
                instructions, tree, map_file, target, args.polls // 100, args.polls // 10
            )
    lines = [f"polled: {args.polls} - {args.polls // 10} polls of the map, median of {args.rounds} rounds"]
    for tree in trees:
        label = "this tree" if tree == ROOT else str(tree)
        line = f"  {label:32} CPU a poll {statistics.median(seconds[tree]) * 1000:7.2f} ms"
        line += f"  ({' '.join(f'{s * 1000:.2f}' for s in seconds[tree])})"
        if tree in counted:
            line += f"  instructions a poll {counted[tree] / 1e6:.2f} M"
        lines.append(line)
    return lines + ["target: a poll costs no more than it did (--before)"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("-n", type=int, default=30, help="runs of each read")
    parser.add_argument("--points", type=int, default=200, help="points in the map (a quarter a table)")
    parser.add_argument("--max-gap", type=int, default=4)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--polls", type=int, default=0, help="also poll the map N times: CPU a poll")
    parser.add_argument("--rounds", type=int, default=3, help="rounds of --polls")
    parser.add_argument(
        "--before",
        type=Path,
        action="append",
        default=[],
        help="an earlier checkout whose polls are measured too (repeatable)",
    )
    parser.add_argument(
        "--instructions", action="store_true", help="with --polls: a poll's instructions too (callgrind)"
    )
    args = parser.parse_args()
    trees = [ROOT] + [tree.resolve() for tree in args.before]
    for tree in trees:
        subprocess.run([sys.executable, "-m", "compileall", "-q", str(tree / "mbtool")], check=True)
    mbtool = Path(sysconfig.get_path("scripts")) / "mbtool"
    if not mbtool.exists():
        sys.exit(f"bench: {mbtool} not found: install mbtool first (pip install -e .)")
    text, fewest = make_map(random.Random(args.seed), args.points // 4, args.max_gap)
    with tempfile.TemporaryDirectory() as tmp:
        map_file = Path(tmp) / "map.toml"
        map_file.write_text(text)
        server = subprocess.Popen(
            [str(mbtool), "serve", "-p", "tcp://127.0.0.1:0", "-q"], stdout=subprocess.PIPE, text=True
        )
        try:
            target = re.search(r"tcp://\S+", server.stdout.readline())[0]
            traced = subprocess.run(
                [str(mbtool), "read", "-m", str(map_file), "-p", target, "--hex", "-o", "json"],
                capture_output=True,
                text=True,
            )
            if traced.returncode:
                sys.exit(f"bench: the map read failed: {traced.stderr.strip()}")
            sent = sum(1 for line in traced.stderr.splitlines() if line.startswith("TX "))
            reads = {
                "one-shot read of 10 registers": [str(mbtool), "read-holding-registers", "0", "10"],
                f"the map, {args.points} points": [str(mbtool), "read", "-m", str(map_file)],
            }
            runs: dict[str, list[float]] = {label: [] for label in reads}
            for command in reads.values():  # warm the caches
                timed([*command, "-p", target, "-o", "json"])
            for _ in range(args.n):
                for label, command in reads.items():
                    runs[label].append(timed([*command, "-p", target, "-o", "json"]))
            polls = polled(args, trees, map_file, target) if args.polls else []
        finally:
            server.terminate()
            server.wait(5)
    print(f"map: {args.points} points over 4 tables, max_gap {args.max_gap}, seed {args.seed}")
    print(f"requests: mbtool sent {sent}, the fewest the limits and max_gap allow {fewest}")
    medians = {label: statistics.median(values) for label, values in runs.items()}
    base = medians["one-shot read of 10 registers"]
    for label, median in medians.items():
        print(
            f"  {label:32} median {median * 1000:6.1f} ms  (min {min(runs[label]) * 1000:.1f})  ratio {median / base:.2f}"
        )
    print(f"target: the map read <= 1.5 x the one-shot read, in the fewest requests; runs {args.n} each")
    for line in polls:
        print(line)


if __name__ == "__main__":
    main()
