#!/usr/bin/env python3
"""Textfile kills: ``read -m MAP --textfile F`` polling back to back, stopped at random moments
with SIGINT, SIGTERM or SIGKILL, while a reader reads F continuously and parses every read
with prometheus_client's text parser, as node_exporter's textfile collector would.

A read is whole when it parses and holds one sample for every point of the map (each
carries its ref label); anything else is a partial read.  Then the planted symlinks: one at
the temporary file's name (``.F.PID.tmp``, planted before the first write) and F itself a
symlink; neither file they point at may change.

Faults: a partial or unparsable read; a symlink followed; a traceback.  The temporary files
left in the folder are counted (after the kills, and after one more uninterrupted run).
"""

from __future__ import annotations

import os
import random
import signal
import subprocess
import threading
import time
from collections import Counter
from pathlib import Path

import common
from prometheus_client.parser import text_string_to_metric_families

SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGKILL)
PRECIOUS = "precious: not mbtool's to write\n"


def make_map(points: int) -> tuple[str, set[str]]:
    """A map of holding registers, input registers and coils (several types, so the file is
    long) and the refs its samples carry."""
    lines, refs = [], set()
    kinds = ("uint16", "int16", "float32", "uint32")
    address = coil = 0
    for i in range(points):
        if i % 5 == 4:
            coil += 1
            ref = f"{coil:05d}"  # coils one after the other: one read takes them all
            lines.append(f'[points.coil_{i}]\nref = "{ref}"\ndescription = "coil number {i}"\n')
        else:
            kind = kinds[i % len(kinds)]
            ref = f"4{address + 1:04d}"
            lines.append(
                f'[points.p{i}_{kind}]\nref = {ref}\ntype = "{kind}"\nunit = "V"\n'
                f'description = "point {i}, a {kind} on holding {address}"\n'
            )
            address += 2 if kind in ("float32", "uint32") else 1
        refs.add(ref)
    return "".join(lines), refs


class Reader(threading.Thread):
    """Reads F over and over; each read must parse and hold a sample of every ref."""

    def __init__(self, path: Path, refs: set[str], report: common.Report) -> None:
        super().__init__(name="textfile-reader", daemon=True)
        self.path, self.refs, self.report = path, refs, report
        self.reads = self.partial = self.absent = 0
        self.stopping = threading.Event()

    def run(self) -> None:
        while not self.stopping.is_set():
            try:
                text = self.path.read_text(encoding="utf-8")
            except FileNotFoundError:
                self.absent += 1
                time.sleep(0.001)
                continue
            except (OSError, UnicodeDecodeError) as error:
                self.partial += 1
                self.report.fault("partial read", f"cannot read: {error}")
                continue
            self.reads += 1
            why = self.judge(text)
            if why:
                self.partial += 1
                self.report.fault(
                    "partial read", f"{why}\n--- the read ({len(text)} characters):\n{text[-800:]}"
                )

    def judge(self, text: str) -> str:
        """Why a read is not whole; "" when it is."""
        try:
            families = list(text_string_to_metric_families(text))
        except Exception as error:  # the parser's ValueError, or anything it chokes on
            return f"unparsable: {type(error).__name__}: {error}"
        found = Counter(sample.labels.get("ref") for family in families for sample in family.samples)
        found.pop(None, None)  # a sample that is no point's (mbtool's own status, if any)
        if set(found) != self.refs or any(count != 1 for count in found.values()):
            missing = sorted(self.refs - set(found))
            return f"{len(found)} of {len(self.refs)} points' samples; missing {missing[:5]}"
        return ""


def temporaries(folder: Path, keep: set[str]) -> list[str]:
    return sorted(name for name in os.listdir(folder) if name not in keep)


def planted_symlinks(target: str, map_path: Path, folder: Path, report: common.Report) -> tuple[int, int]:
    """(symlinks followed of 2, runs); a slow device holds the first write back long enough
    for the link to be planted at the temporary name, which holds the new process's id."""
    followed = 0
    outside = folder / "outside"
    outside.mkdir()
    checks = [("at the temporary file's name", "temporary"), ("at F", "file")]
    for label, where in checks:
        victim = outside / f"victim-{where}"
        victim.write_text(PRECIOUS)
        textfile = folder / f"linked-{where}.prom"
        if where == "file":
            textfile.symlink_to(victim)
        proc = common.popen("read", "-m", map_path, "--textfile", textfile, "--polls", "1", "-p", target)
        if where == "temporary":
            (folder / f".{textfile.name}.{proc.pid}.tmp").symlink_to(victim)
        out, err = proc.communicate(timeout=60)
        err = err.decode(errors="replace")
        if "Traceback (most recent call last)" in err:
            report.fault("traceback", err[-2000:])
        if victim.read_text() != PRECIOUS:
            followed += 1
            report.fault(
                "symlink followed",
                f"a symlink {label} -> {victim}: that file now holds {victim.read_text()[:200]!r}\nexit {proc.returncode} {err[-500:]}",
            )
    return followed, len(checks)


def main() -> None:
    args = common.arguments(
        __doc__,
        kills=(int, 36, "polling runs to stop"),
        points=(int, 120, "points in the map (the file is about 140 bytes a point)"),
    )
    rng = random.Random(args.seed)
    report = common.Report("textfile kills", args.verbose)
    kills = Counter()
    codes = Counter()
    tracebacks = 0
    with common.scratch("textfile") as folder:
        folder = Path(folder)
        text, refs = make_map(args.points)
        map_path = folder / "plant.toml"
        map_path.write_text(text)
        exported = folder / "exported"
        exported.mkdir()
        textfile = exported / "plant.prom"
        reader = Reader(textfile, refs, report)
        with common.serve() as device:
            reader.start()
            try:
                for _ in range(args.kills):
                    sig = rng.choice(SIGNALS)
                    proc = common.popen(
                        "read", "-m", map_path, "--textfile", textfile, "--interval", "0", "-p", device.target
                    )
                    time.sleep(
                        rng.uniform(0.3, 1.5)
                    )  # start-up is about 0.3 s: a few kills come before a write
                    proc.send_signal(sig)
                    try:
                        _, err = proc.communicate(timeout=20)
                    except subprocess.TimeoutExpired:
                        proc.kill()
                        _, err = proc.communicate()
                        report.fault("hang", f"did not end 20 s after {sig.name}")
                    err = err.decode(errors="replace")
                    kills[sig.name] += 1
                    codes[proc.returncode] += 1
                    if "Traceback (most recent call last)" in err and "KeyboardInterrupt" not in err:
                        tracebacks += 1
                        report.fault("traceback", err[-2000:])
            finally:
                reader.stopping.set()
                reader.join(5)
            left_by_kills = temporaries(exported, {textfile.name})
            clean = common.run(
                "read", "-m", map_path, "--textfile", textfile, "--polls", "1", "-p", device.target
            )
            if clean.code != 0:
                report.fault("an uninterrupted run failed", str(clean))
            left_after = temporaries(exported, {textfile.name})
            with common.serve("--delay", "0.3") as slow:
                followed, checks = planted_symlinks(slow.target, map_path, folder, report)
        size = textfile.stat().st_size if textfile.exists() else 0
    report.figure(
        "kills", f"{sum(kills.values())} ({', '.join(f'{k} {n}' for k, n in sorted(kills.items()))})"
    )
    report.figure("exit codes", ", ".join(f"{code}: {n}" for code, n in sorted(codes.items(), key=str)))
    report.figure("textfile", f"{args.points} points, {size} bytes")
    report.figure("reads", f"{reader.reads} (and {reader.absent} before the first write)")
    report.figure("partial or unparsable reads (must be 0)", reader.partial)
    report.figure("temporary files left by the kills", len(left_by_kills))
    report.figure("temporary files left after one more clean run", len(left_after))
    report.figure("planted symlinks followed (must be 0)", f"{followed} of {checks}")
    report.figure("tracebacks (must be 0)", tracebacks)
    report.finish()


if __name__ == "__main__":
    main()
