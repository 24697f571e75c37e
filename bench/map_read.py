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

Run by hand:  python bench/map_read.py [-n 30] [--max-gap 4] [--seed 1]
"""

from __future__ import annotations

import argparse
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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("-n", type=int, default=30, help="runs of each read")
    parser.add_argument("--points", type=int, default=200, help="points in the map (a quarter a table)")
    parser.add_argument("--max-gap", type=int, default=4)
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args()
    subprocess.run([sys.executable, "-m", "compileall", "-q", str(ROOT / "mbtool")], check=True)
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


if __name__ == "__main__":
    main()
