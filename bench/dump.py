#!/usr/bin/env python3
"""What ``mbtool dump`` costs on a sparse device: 10,000 registers scattered over holding 0-65535.

Serves a sparse data file with ``mbtool serve`` (seeded, so every run is the same
device), dumps its holding registers, and prints the requests and the time beside two
floors: one request per readable block (what a dump that knew the address map would
send) and one request per hole plus one per block (what any exact dump must send: a
refused read confirms at most one missing address).  Checks that the dump found every
register.  Run by hand:  python bench/dump.py [--registers 10000] [--blocky]
"""

from __future__ import annotations

import argparse
import random
import re
import subprocess
import sys
import tempfile
import time
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
from mbtool.link.dump import runs_of  # noqa: E402  (the bench runs from a checkout)


def device(registers: int, blocky: bool, rng: random.Random) -> list[int]:
    if blocky:  # blocks of 10..200 registers with gaps between
        present: set[int] = set()
        while len(present) < registers:
            first, size = rng.randrange(65536), rng.randint(10, 200)
            present.update(range(first, min(65536, first + size)))
        return sorted(present)[:registers]
    return sorted(rng.sample(range(65536), registers))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--registers", type=int, default=10000)
    parser.add_argument("--blocky", action="store_true", help="registers in blocks, not one by one")
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args()
    present = device(args.registers, args.blocky, random.Random(args.seed))
    blocks = runs_of(present)
    with tempfile.TemporaryDirectory() as tmp:
        data = Path(tmp) / "device.toml"
        lines = ["sparse = true", "[holding_registers]"]
        lines += [
            f"{first} = [{', '.join(str(a & 0xFFFF) for a in range(first, last + 1))}]"
            for first, last in blocks
        ]
        data.write_text("\n".join(lines) + "\n")
        server = subprocess.Popen(
            [sys.executable, "-m", "mbtool", "serve", "-p", "tcp://127.0.0.1:0", "-q", "--data", str(data)],
            stdout=subprocess.PIPE,
            text=True,
            cwd=ROOT,
        )
        try:
            line = server.stdout.readline()
            target = re.search(r"tcp://\S+", line)[0]
            out = Path(tmp) / "dump.toml"
            began = time.monotonic()
            result = subprocess.run(
                [sys.executable, "-m", "mbtool", "dump", str(out), "--range", "holding", "-p", target],
                capture_output=True,
                text=True,
                cwd=ROOT,
            )
            elapsed = time.monotonic() - began
            dumped = tomllib.loads(out.read_text()) if out.exists() else {}
        finally:
            server.terminate()
            server.wait(5)
    if result.returncode:
        sys.exit(f"bench: dump failed: {result.stderr.strip()}")
    requests = int(re.search(r"(\d+) requests", result.stderr)[1])
    refused = re.search(r"\((\d+) refused", result.stderr)
    refused = int(refused[1]) if refused else 0
    found = []
    for key, values in dumped.get("holding_registers", {}).items():
        count = values["count"] if isinstance(values, dict) else len(values)
        found += range(int(key), int(key) + count)
    if sorted(found) != present:
        sys.exit("bench: the dump does not hold exactly the device's registers")
    holes = 65536 - len(present)
    print(
        f"device: {len(present)} holding registers in {len(blocks)} blocks, {holes} holes ({'blocks' if args.blocky else 'scattered'})"
    )
    print(f"dump:   {requests} requests in {elapsed:.1f} s   ({result.stderr.strip()})")
    print(f"floor, one request per block:           {len(blocks)}")
    print(
        f"floor, exact (one per hole + per block): {holes + len(blocks)}   dump / exact floor = {requests / (holes + len(blocks)):.2f}"
    )
    # Target (issue: fast where it counts): reads answered with data at most 2 x the blocks;
    # the bisection's exception replies come on top.
    answered = requests - refused
    print(
        f"answered reads: {answered} = {answered / len(blocks):.2f} x the blocks (target <= 2), "
        f"plus {refused} exception replies of the bisection"
    )


if __name__ == "__main__":
    main()
