#!/usr/bin/env python3
"""Hostile inventories: poll's inventories that no plant should have, fed to ``mbtool poll``.

A catalogue of careless and hostile inventories, each built once: maps and inventories that
are no regular file (/dev/zero, a FIFO, a symbolic link to /dev/zero, a directory) or are
past the size bound, two links on one target however spelled, a max_backoff below the
interval, a device's own timeout and retries of the wrong kind, numbers TOML allows and no
plant means (nan, 1e308), bytes that are not UTF-8, deep nesting, a --textfile in no
folder, a --hex-link the inventory lacks, and more links than the process may have threads.
Then random inventories: one link through a recording proxy to ``mbtool serve -u 1-2`` and
perhaps a sim:// one, 1-3 devices each (unit 9 never answers), their interval, max_backoff,
offline_after, timeout, retries and unit drawn from sensible and hostile values, run with
--once, --rounds 2 or --duration 1.

Every run has its address space capped (1 GiB: a reader that runs away fails fast, not with
the machine's memory) and a deadline.  Faults: a traceback (MBTOOL_DEBUG=1), a run past its
deadline, a refusal (exit 2) that is not one line or that connected or sent a byte, a
catalogue case not refused with its exit code, and a next try announced in a run that ends
before it (``next try in`` under --once).
"""

from __future__ import annotations

import math
import os
import random
import resource
from collections import Counter
from pathlib import Path

import common

ADDRESS_SPACE = 1 << 30
TOO_BIG = (16 << 20) + 1  # mbtool.files.MAX_FILE_BYTES + 1


def _capped() -> None:
    common.signals_as_from_a_shell()
    resource.setrlimit(resource.RLIMIT_AS, (ADDRESS_SPACE, ADDRESS_SPACE))


def run(*args: object, deadline: float = common.RUN_DEADLINE) -> common.Run:
    """mbtool ARGS to its end, its address space capped; past the deadline it is killed (code None)."""
    return common.run(*args, deadline=deadline, preexec_fn=_capped)


def device(name: str, link: str, extra: str = "", read: str = '["40001"]') -> str:
    return f'[devices.{name}]\nlink = "{link}"\nread = {read}\n{extra}'


def catalogue(folder: Path, target: str) -> list[tuple[str, Path, list[str], int]]:
    """(name, inventory, poll's other arguments, the exit code it must have)."""
    fifo = folder / "fifo.toml"
    os.mkfifo(fifo)
    big = folder / "big.toml"
    with open(big, "wb") as file:
        file.truncate(TOO_BIG)
    zero_link = folder / "zero.toml"
    zero_link.symlink_to("/dev/zero")
    (folder / "ttyS7").write_text("")
    (folder / "by-id").mkdir()
    (folder / "by-id" / "usb-port").symlink_to(folder / "ttyS7")
    port = target.rsplit(":", 1)[1]
    link = f'[links.a]\ntarget = "{target}"\n'
    one = link + device("d", "a")
    cases: list[tuple[str, str | Path, list[str], int]] = [
        ("map /dev/zero", link + device("d", "a", 'map = "/dev/zero"\n', read="[]").replace("read = []\n", ""), [], 2),
        ("map a FIFO", link + f'[devices.d]\nlink = "a"\nmap = "{fifo}"\n', [], 2),
        ("map a symlink to /dev/zero", link + f'[devices.d]\nlink = "a"\nmap = "{zero_link}"\n', [], 2),
        ("map past the size bound", link + f'[devices.d]\nlink = "a"\nmap = "{big}"\n', [], 2),
        ("map a directory", link + f'[devices.d]\nlink = "a"\nmap = "{folder}"\n', [], 2),
        ("inventory a FIFO", fifo, [], 2),
        ("inventory /dev/zero", Path("/dev/zero"), [], 2),
        ("inventory past the size bound", big, [], 2),
        ("two links, one target", link + f'[links.b]\ntarget = "{target}/"\n' + device("d", "a") + device("e", "b"), [], 2),
        ("tcp:// and socket:// on one port", link + f'[links.b]\ntarget = "socket://127.0.0.1:{port}"\n'
         + device("d", "a") + device("e", "b"), [], 2),
        ("IPv4 and IPv4-mapped IPv6", link + f'[links.b]\ntarget = "tcp://[::ffff:127.0.0.1]:{port}"\n'
         + device("d", "a") + device("e", "b"), [], 2),
        ("a serial port and a link to it", f'[links.a]\ntarget = "{folder}/ttyS7"\n[links.b]\n'
         f'target = "{folder}/by-id/usb-port"\n' + device("d", "a") + device("e", "b"), [], 2),
        ("max_backoff below the interval, [poll]", "[poll]\ninterval = 2\nmax_backoff = 0.5\n" + one, [], 2),
        ("max_backoff below the interval, device", link + device("d", "a", "interval = 5\nmax_backoff = 1\n"), [], 2),
        ("max_backoff 1e-9", link + device("d", "a", "max_backoff = 1e-9\n"), [], 2),
        ("interval nan", link + device("d", "a", "interval = nan\n"), [], 2),
        ("interval 1e308", link + device("d", "a", "interval = 1e308\n"), [], 2),
        ("device timeout 0", link + device("d", "a", "timeout = 0\n"), [], 2),
        ("device timeout -1", link + device("d", "a", "timeout = -1\n"), [], 2),
        ("device timeout inf", link + device("d", "a", "timeout = inf\n"), [], 2),
        ("device timeout text", link + device("d", "a", 'timeout = "fast"\n'), [], 2),
        ("device retries -1", link + device("d", "a", "retries = -1\n"), [], 2),
        ("device retries 1.5", link + device("d", "a", "retries = 1.5\n"), [], 2),
        ("device retries true", link + device("d", "a", "retries = true\n"), [], 2),
        ("device retries 10**9", link + device("d", "a", "retries = 1000000000\n"), [], 2),
        ("not UTF-8", one.encode().replace(b"[devices.d]", b"[devices.\xff]").decode("latin-1"), [], 2),
        ("nested 100,000 deep", one + "x = " + "[" * 100_000 + "]" * 100_000 + "\n", [], 2),
        ("--textfile in no folder", one, ["--textfile", str(folder / "nosuch" / "plant.prom")], 7),
        ("--hex-link of no link", one, ["--hex-link", "nosuch"], 2),
        ("400 links, more than the threads allowed",
         "".join(f'[links.l{i}]\ntarget = "sim://"\n' + device(f"d{i}", f"l{i}") for i in range(400)), [], 6),
    ]  # fmt: skip
    built = []
    for index, (name, text, extra, code) in enumerate(cases):
        if isinstance(text, Path):
            built.append((name, text, extra, code))
            continue
        path = folder / f"case{index}.toml"
        path.write_bytes(text.encode("latin-1") if name == "not UTF-8" else text.encode())
        built.append((name, path, extra, code))
    return built


# Each key's sensible values, then its hostile ones; a key is hostile one time in four.
CHOICES = {
    "interval": ([0.05, 0.2, 0.5], [0, -1, math.nan, math.inf, 1e308, '"2"', "true"]),
    "max_backoff": ([0.5, 1, 5], [0.01, 0.1, 0, math.nan]),
    "offline_after": ([1, 2, 3], [0, -1, 1.5]),
    "timeout": ([0.05, 0.1, 0.2], [0, -0.1, math.nan, '"x"']),
    "retries": ([0, 1, 2], [-1, 1.5, 101, "true"]),
    "unit": ([1, 2, 9], [0, 255, 256, -1]),
}


def toml_value(value) -> str:
    if isinstance(value, float) and math.isnan(value):
        return "nan"
    if isinstance(value, float) and math.isinf(value):
        return "inf"
    return str(value)


def random_inventory(
    rng: random.Random, folder: Path, index: int, target: str
) -> tuple[Path, list[str], float]:
    """A random inventory, poll's ending, and the longest the run may take if it is accepted."""
    text = f'[links.gw]\ntarget = "{target}"\ntimeout = 0.1\n'
    sim = rng.random() < 0.3
    if sim:
        text += '[links.bus]\ntarget = "sim://"\n'
    longest = 0.0
    for number in range(rng.randint(1, 3)):
        keys = rng.sample(sorted(CHOICES), rng.randint(0, 4))
        text += (
            f'[devices.d{number}]\nlink = "{"bus" if sim and number == 2 else "gw"}"\nread = ["40001 2"]\n'
        )
        if number and rng.random() < 0.3:
            keys = [key for key in keys if key != "unit"]
            text += "unit = 9\n"  # a unit serve does not answer: offline, backed off
        timeout, retries = 0.1, 0
        for key in keys:
            sensible, hostile = CHOICES[key]
            value = rng.choice(hostile if rng.random() < 0.25 else sensible)
            text += f"{key} = {toml_value(value)}\n"
            if key == "timeout" and isinstance(value, float) and value > 0:
                timeout = value
            if key == "retries" and isinstance(value, int) and value > 0:
                retries = value
        longest += timeout * (retries + 1) * 3
    ending = rng.choice([["--once"], ["--rounds", "2"], ["--duration", "1"]])
    path = folder / f"random{index}.toml"
    path.write_text(text)
    return path, ending, longest + 2


def main() -> None:
    args = common.arguments(__doc__, inventories=(int, 40, "random inventories after the catalogue"))
    rng = random.Random(args.seed)
    report = common.Report("hostile inventories", args.verbose)
    codes: Counter = Counter()
    refused = accepted = 0
    with common.scratch("inventories") as folder, common.serve("-u", "1-2") as served:
        folder = Path(folder)
        proxy = common.RecordingProxy((served.host, served.port))
        try:
            cases = catalogue(folder, proxy.target)
            caught = 0
            for name, path, extra, code in cases:
                proxy.take()
                result = run("poll", path, "--once", "-o", "json", *extra)
                connections, sent, _ = proxy.take()
                shown = f"[{name}]\n{result}"
                judge(report, result, shown, connections or sent)
                if result.code != code:
                    report.fault(
                        "catalogue case not refused as it should be", f"(wanted exit {code})\n{shown}"
                    )
                elif connections or sent or result.out:
                    report.fault("catalogue case opened a link", shown)
                else:
                    caught += 1
            report.figure(
                "catalogue",
                f"{len(cases)} hostile inventories, {caught} refused with their code, nothing opened",
            )
            for index in range(args.inventories):
                path, ending, longest = random_inventory(rng, folder, index, proxy.target)
                proxy.take()
                result = run(
                    "poll", path, *ending, "-o", "json", deadline=min(longest + 10, common.RUN_DEADLINE)
                )
                connections, sent, _ = proxy.take()
                shown = f"{result}\n(inventory: {path.read_text()[:800]})"
                codes["hang" if result.hung else result.code] += 1
                judge(report, result, shown, connections or sent)
                if result.code == 2:
                    refused += 1
                else:
                    accepted += 1
                    if ending == ["--once"] and "next try in" in result.err:
                        report.fault("next try announced in a --once run", shown)
        finally:
            proxy.close()
    report.figure("random inventories", f"{args.inventories} ({refused} refused at load, {accepted} polled)")
    report.figure("exit codes, random", ", ".join(f"{c}: {n}" for c, n in sorted(codes.items(), key=str)))
    report.figure("faults by kind (each must be 0)", dict(report.faults) or 0)
    report.finish()


def judge(report: common.Report, result: common.Run, shown: str, touched: int) -> None:
    """The faults any run can have."""
    if result.hung:
        report.fault("run past its deadline", shown)
    if result.traceback:
        report.fault("traceback", shown)
    if result.code == 2:
        lines = result.err.splitlines()
        if len(lines) != 1 or not lines[0].startswith("mbtool: "):
            report.fault("a refusal that is not one line", shown)
        if touched:
            report.fault("exit 2 after connecting", shown)


if __name__ == "__main__":
    main()
