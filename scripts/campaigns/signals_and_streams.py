#!/usr/bin/env python3
"""Random signals and closed streams (issue 40.8, 40.14): what a shell, a terminal closing, a
service manager or a careless cron line does to mbtool's long and short commands.

* signals: ``poll``, ``read --interval``, ``dump``, ``sunspec``, ``exporter``, ``serve`` and
  ``bridge`` (against ``mbtool serve``; the bridge in front of a pseudo-terminal bus) get
  SIGINT, SIGTERM, SIGHUP or SIGPIPE at a random moment 0.3-2.5 s after they start; a
  command still running 1 s after a SIGPIPE (which a program that writes to no closed pipe
  may ignore) gets SIGTERM.  Every output is held to its format's parser (JSON lines, CSV
  rows of the header's width, influx lines by line_protocol_parser, Prometheus text by
  prometheus_client's parser, dump files by tomllib) and the exit code to
  docs/exit-codes.md: SIGINT and SIGTERM end the servers with 0, ``poll`` and
  ``read --interval`` by their verdict (0 here, every device answers) or 130 before their
  first poll ended, ``dump`` and ``sunspec`` with 130 unless they had finished (0); SIGHUP
  as SIGTERM.
* streams: each command family run with stdin closed (``<&-``), stdout closed (``>&-``),
  stderr closed (``2>&-``), stdout on /dev/full and stderr on /dev/full, beside a run with
  every stream open: with stdin or stderr closed, or stderr full, the same exit code and
  stdout of data only; with stdout closed 141 (the docs' "a stdout closed before the
  start"), quietly; with stdout full 7 and one line on stderr; a command that writes
  nothing to stdout keeps its code.

Faults: a traceback (or exit 1, an internal error, where stderr is closed); an output line
cut or that its parser refuses; a line for the human (``mbtool:``) on stdout; anything but
one line on stderr where stdout is full; a wrong exit code; a temporary file left in the
dump's folder; a command that did not end within 10 s of its signal.
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
import os
import random
import re
import signal
import subprocess
import threading
import time
import tomllib
from collections import Counter
from pathlib import Path

import common

FORMATS = ("json", "csv", "influx", "prom")
SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP, signal.SIGPIPE)
ENDS = 10.0  # seconds a command may take to end after its signal


def judge_output(kind: str, text: str) -> str:
    """Why ``text`` is not a whole output of format ``kind`` ("" when it is)."""
    if not text:
        return ""
    if not text.endswith("\n"):
        return f"the last line is cut: {text[-200:]!r}"
    lines = text.splitlines()
    for line in lines:
        if line.startswith("mbtool:"):
            return f"a line for the human on stdout: {line!r}"
    if kind == "json":
        for line in lines:
            try:
                json.loads(line)
            except ValueError:
                return f"not JSON: {line[:200]!r}"
    elif kind == "csv":
        rows = list(csv.reader(io.StringIO(text)))
        width = len(rows[0])
        for row in rows:
            if len(row) != width:
                return f"a CSV row of {len(row)} fields, the header has {width}: {row[:6]}"
    elif kind == "influx":
        import line_protocol_parser  # noqa: PLC0415 - a test dependency, for this format only

        for line in lines:
            try:
                line_protocol_parser.parse_line(line)
            except Exception as error:  # noqa: BLE001 - whatever it refuses is the fault
                return f"not line protocol ({error}): {line[:200]!r}"
    elif kind == "prom":
        from prometheus_client.parser import text_string_to_metric_families  # noqa: PLC0415

        try:
            list(text_string_to_metric_families(text))
        except Exception as error:  # noqa: BLE001
            return f"not Prometheus text ({error}): {text[-300:]!r}"
    return ""


class Plant:
    """The peers: ``mbtool serve`` of the energy meter's data, a slow one for ``dump``, a SunSpec
    twin, a pseudo-terminal bus for the bridge, and the inventories."""

    def __init__(self, stack: contextlib.ExitStack, folder: Path) -> None:
        data = common.ROOT / "examples"
        self.folder = folder
        self.fast = stack.enter_context(common.serve("-u", "1-2", "--data", data / "energy-meter-data.toml"))
        self.slow = stack.enter_context(common.serve("-u", "1", "--delay", "0.01"))
        self.sun = stack.enter_context(common.serve("--delay", "0.03", "--data", data / "sunspec-twin.toml"))
        self.bus = common.PtyPair()
        stack.callback(self.bus.close)
        if not (self.fast.target and self.slow.target and self.sun.target):
            common.give_up("mbtool serve did not say where it listens")
        self.inventory = folder / "plant.toml"
        self.inventory.write_text(
            f'[poll]\ninterval = 0.05\n[links.gw]\ntarget = "{self.fast.target}"\n'
            '[devices.pump]\nlink = "gw"\nunit = 1\nread = ["40001 4", "00001 8"]\n'
            f'[devices.meter]\nlink = "gw"\nunit = 2\nmap = "{data / "energy-meter.toml"}"\n'
        )
        self.with_dead = folder / "dead.toml"
        self.with_dead.write_text(
            self.inventory.read_text()
            + '[devices.meter9]\nlink = "gw"\nunit = 9\ntimeout = 0.2\nread = ["40001 1"]\n'
        )
        self.dumps = folder / "dumps"
        self.dumps.mkdir()


# --- random signals ------------------------------------------------------------------------


def signal_case(plant: Plant, rng: random.Random, number: int) -> tuple[str, str, list[object], set[int]]:
    """(name, output kind, arguments, exit codes SIGINT/SIGTERM may give)."""
    name = rng.choice(["poll", "read", "dump", "sunspec", "exporter", "serve", "bridge"])
    fmt = rng.choice(FORMATS)
    if name == "poll":
        return name, fmt, ["poll", plant.inventory, "-o", fmt], {0, 130}
    if name == "read":
        args = ["read", "-p", plant.fast.target, "40001", "10", "--interval", "0.05", "-o", fmt]
        return name, fmt, args, {0, 130}
    if name == "dump":
        return name, "dump", ["dump", "-p", plant.slow.target, plant.dumps / f"d{number}.toml"], {0, 130}
    if name == "sunspec":
        fmt = rng.choice(["json", "plain"])
        return name, fmt, ["sunspec", "-p", plant.sun.target, "-o", fmt], {0, 130}
    if name == "exporter":
        return name, "server", ["exporter", plant.inventory, "--listen", "127.0.0.1:0"], {0}
    if name == "serve":
        return name, "server", ["serve", "-p", "tcp://127.0.0.1:0", "-u", "1"], {0}
    args = ["bridge", "--listen", "tcp://127.0.0.1:0", "-p", plant.bus.mbtool_path, *common.PTY_SERIAL_OPTS]
    return name, "server", args, {0}


def signals(plant: Plant, runs: int, rng: random.Random, report: common.Report) -> None:
    outcomes: Counter[str] = Counter()
    for number in range(runs):
        name, kind, args, codes = signal_case(plant, rng, number)
        sig = rng.choice(SIGNALS)
        proc = common.popen(*args)
        taken: dict[str, bytes] = {}

        def read(proc=proc, taken=taken) -> None:
            taken["out"], taken["err"] = proc.communicate()

        reader = threading.Thread(target=read)
        reader.start()
        time.sleep(rng.uniform(0.3, 2.5))
        sent = signal.Signals(sig).name
        if proc.poll() is not None:  # it had finished: what it did is judged all the same
            sent, codes = "none (it had ended)", {0}
        proc.send_signal(sig)
        if sig == signal.SIGPIPE and proc.poll() is None:
            with contextlib.suppress(subprocess.TimeoutExpired):
                proc.wait(1)
            if proc.poll() is None:
                sent += " (ignored), SIGTERM"
                proc.send_signal(signal.SIGTERM)
        reader.join(ENDS)
        shown = f"$ mbtool {' '.join(map(str, args))}  <- {sent}"
        if reader.is_alive():
            report.fault("no end within 10 s of the signal", shown)
            proc.kill()
            reader.join(5)
            continue
        code = proc.returncode
        out, err = taken["out"].decode(errors="replace"), taken["err"].decode(errors="replace")
        outcomes[f"{name} {sent.split()[0]} -> {code}"] += 1
        shown += f"\n-> exit {code}\n{err[-2000:]}"
        if "Traceback (most recent call last)" in err:
            report.fault("traceback", shown)
        expected = codes  # SIGHUP is a SIGTERM (docs/exit-codes.md)
        if code not in expected:
            report.fault("wrong exit code", f"expected {sorted(expected)}\n{shown}")
        if kind == "dump":
            path = Path(str(args[-1]))
            if path.exists():
                try:
                    tomllib.loads(path.read_text())
                except (tomllib.TOMLDecodeError, UnicodeDecodeError) as error:
                    report.fault("a dump file cut or unreadable", f"{error}\n{shown}")
            left = [p.name for p in plant.dumps.iterdir() if not re.fullmatch(r"d\d+\.toml", p.name)]
            if left:
                report.fault("a temporary file left", f"{left}\n{shown}")
                for stray in left:
                    (plant.dumps / stray).unlink()
        elif kind != "server":
            why = judge_output(kind if kind != "plain" else "", out)
            if why:
                report.fault("a cut or unparsable output", f"{why}\n{shown}")
        elif out and not out.endswith("\n"):
            report.fault("a cut or unparsable output", f"{out[-200:]!r}\n{shown}")
    report.figure("signals: runs", runs)
    for outcome, count in sorted(outcomes.items()):
        report.figure(f"  {outcome}", count)


# --- closed streams ------------------------------------------------------------------------


def families(plant: Plant) -> list[tuple[str, str, list[object], bool]]:
    """(name, output kind, arguments, runs until stopped)."""
    fast = plant.fast.target
    return [
        ("read", "json", ["read", "-p", fast, "40001", "4", "-o", "json"], False),
        (
            "read -m",
            "csv",
            ["read", "-p", fast, "-u", "2", "-m", common.ROOT / "examples/energy-meter.toml", "-o", "csv"],
            False,
        ),  # fmt: skip
        (
            "read --interval",
            "influx",
            ["read", "-p", fast, "40001", "4", "--interval", "0.05", "--polls", "5", "-o", "influx"],
            False,
        ),
        ("read-holding-registers", "", ["read-holding-registers", "-p", fast, "0", "3"], False),
        ("write-register", "", ["write-register", "-p", fast, "100", "7"], False),
        ("poll --once", "json", ["poll", plant.with_dead, "--once", "-o", "json"], False),
        ("poll --rounds", "prom", ["poll", plant.inventory, "--rounds", "3", "-o", "prom"], False),
        ("dump -", "dump", ["dump", "-p", fast, "-u", "2", "-"], False),
        ("sunspec", "json", ["sunspec", "-p", plant.sun.target, "-o", "json"], False),
        ("ping", "", ["ping", "-p", fast, "-c", "3", "-i", "0.05"], False),
        ("scan", "", ["scan", "-p", fast, "-u", "1-3", "-t", "0.2"], False),
        ("maps list", "", ["maps", "list"], False),
        ("decode", "", ["decode", "--framer", "rtu", "01 03 02 00 2a 38 5b"], False),
        ("exporter", "", ["exporter", plant.inventory, "--listen", "127.0.0.1:0"], True),
        ("serve", "", ["serve", "-p", "tcp://127.0.0.1:0", "-u", "1"], True),
        (
            "bridge",
            "",
            ["bridge", "--listen", "tcp://127.0.0.1:0", "-p", plant.bus.mbtool_path, *common.PTY_SERIAL_OPTS],
            True,
        ),  # fmt: skip
    ]


def run_with_streams(args: list[object], closed: tuple[int, ...], full: tuple[int, ...], server: bool):
    """mbtool ARGS with the descriptors ``closed`` closed and ``full`` on /dev/full: (exit code,
    stdout, stderr), None for a stream not captured; the code None for a hang."""

    def prepare() -> None:
        common.signals_as_from_a_shell()
        for fd in full:
            devfull = os.open("/dev/full", os.O_WRONLY)
            os.dup2(devfull, fd)
            os.close(devfull)
        for fd in closed:
            os.close(fd)

    proc = subprocess.Popen(
        common.argv(*args),
        cwd=common.TREE,
        env=common.env(),
        preexec_fn=prepare,
        stdin=subprocess.DEVNULL,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )
    if server:
        time.sleep(1.5)
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
    try:
        out, err = proc.communicate(timeout=common.RUN_DEADLINE)
        code = proc.returncode
    except subprocess.TimeoutExpired:
        proc.kill()
        out, err = proc.communicate()
        code = None
    return code, out.decode(errors="replace"), err.decode(errors="replace")


def streams(plant: Plant, report: common.Report) -> None:
    table: list[str] = []
    for name, kind, args, server in families(plant):
        base_code, base_out, base_err = run_with_streams(args, (), (), server)
        row = [f"{name}: open {base_code}"]
        shown = f"$ mbtool {' '.join(map(str, args))}"
        if base_code is None or "Traceback" in base_err:
            report.fault("traceback", f"{shown} (every stream open)\n{base_err[-2000:]}")
        writes = bool(base_out)
        for label, closed, full in (
            ("<&-", (0,), ()),
            (">&-", (1,), ()),
            ("2>&-", (2,), ()),
            (">/dev/full", (), (1,)),
            ("2>/dev/full", (), (2,)),
        ):
            code, out, err = run_with_streams(args, closed, full, server)
            row.append(f"{label} {code}")
            case = f"{shown} {label}\n-> exit {code} (open: {base_code})\nstdout: {out[-600:]!r}\nstderr: {err[-1500:]}"
            if code is None:
                report.fault("a hang", case)
                continue
            if "Traceback (most recent call last)" in err or (2 in closed + full and code == 1):
                report.fault("traceback", case)
            if 1 in closed:
                expected = 141 if writes else base_code
                if server:
                    expected = {141, base_code}
                if code not in (expected if isinstance(expected, set) else {expected}):
                    report.fault("wrong exit code", f"expected {expected}\n{case}")
                if err.strip() and not server:
                    report.fault("stderr not quiet when stdout is closed", case)
            elif 1 in full:
                expected = 7 if writes else base_code
                if code != expected and not (server and code == base_code):
                    report.fault("wrong exit code", f"expected {expected}\n{case}")
                if writes and not re.search(r"cannot write to standard output", err):
                    report.fault("stdout full: not said", case)
            else:
                if code != base_code:
                    report.fault("wrong exit code", f"expected {base_code}\n{case}")
                why = judge_output(kind if kind not in ("", "dump") else "", out)
                if kind == "dump" and out:
                    try:
                        tomllib.loads(out)
                    except tomllib.TOMLDecodeError as error:
                        why = f"not TOML: {error}"
                if not why and out.count("\n") != base_out.count("\n") and not server:
                    why = f"{out.count(chr(10))} lines, {base_out.count(chr(10))} with stderr open"
                if "mbtool:" in out:
                    why = why or "a line for the human on stdout"
                if why:
                    report.fault("stdout not data only", f"{why}\n{case}")
        table.append(", ".join(row))
    report.figure("streams: runs", len(table) * 6)
    for line in table:
        report.figure("  exit codes", line)


def main() -> None:
    args = common.arguments(__doc__, runs=(int, 40, "random-signal runs"))
    rng = random.Random(args.seed)
    report = common.Report("random signals and closed streams", args.verbose)
    with common.scratch("signals") as scratch, contextlib.ExitStack() as stack:
        plant = Plant(stack, Path(scratch))
        signals(plant, args.runs, rng, report)
        streams(plant, report)
    report.finish()


if __name__ == "__main__":
    main()
