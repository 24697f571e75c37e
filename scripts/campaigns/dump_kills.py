#!/usr/bin/env python3
"""Dump kills: ``mbtool dump`` of a slow ``mbtool serve``, stopped at random moments.

Each run starts from a previous, complete dump at the target path, then dumps the device
again and stops it, at a random moment after its link opened, with SIGINT, SIGINT twice,
SIGINT then SIGTERM, SIGTERM, SIGKILL, or SIGTERM then SIGKILL (a service manager's stop).
The file left is read with tomllib.

Faults: a 0-byte, partial or missing file (the previous dump destroyed); a run stopped
by SIGINT or SIGTERM, after replies had come, that saved nothing; a traceback; a run that
did not end within 20 s of its last signal.  SIGKILL cannot be saved from; it may keep the
previous dump or leave the new one, never a broken file.
"""

from __future__ import annotations

import random
import signal
import subprocess
import time
import tomllib
from collections import Counter
from pathlib import Path

import common

KINDS = {
    "SIGINT": (signal.SIGINT,),
    "SIGINT twice": (signal.SIGINT, signal.SIGINT),
    "SIGINT, SIGTERM": (signal.SIGINT, signal.SIGTERM),
    "SIGTERM": (signal.SIGTERM,),
    "SIGKILL": (signal.SIGKILL,),
    "SIGTERM, SIGKILL": (signal.SIGTERM, signal.SIGKILL),
}
# The second signal comes 1 ms to 250 ms after the first, log-uniformly: as often in the few
# milliseconds a dump takes to write its file as in the rest.
SECOND_AFTER = (0.001, 0.25)
END_DEADLINE = 20.0  # seconds a dump may take to end after its last signal
STATES = ("new, complete", "new, complete = false", "previous kept", "0 bytes", "partial", "missing")


def device_data(registers: int, rng: random.Random) -> str:
    """A device with every address of holding and coils 0..registers-1, random values (so the
    dump is long text, not runs) and an identity to read at the end."""
    holding = ", ".join(str(rng.randrange(65536)) for _ in range(registers))
    coils = ", ".join(str(rng.randrange(2)) for _ in range(registers))
    return (
        f"sparse = true\n[holding_registers]\n0 = [{holding}]\n[coils]\n0 = [{coils}]\n"
        '[identity]\nvendor_name = "campaign"\nproduct_code = "dump-kills"\nrevision = "1"\n'
    )


def state_of(path: Path, previous: bytes) -> str:
    if not path.exists():
        return "missing"
    data = path.read_bytes()
    if data == previous:
        return "previous kept"
    if not data:
        return "0 bytes"
    try:
        document = tomllib.loads(data.decode("utf-8"))
    except (UnicodeDecodeError, tomllib.TOMLDecodeError):
        return "partial"
    if document.get("sparse") is not True:
        return "partial"
    return "new, complete = false" if document.get("complete") is False else "new, complete"


def wait_for_link(proxy: common.RecordingProxy, proc: subprocess.Popen, deadline: float = 20) -> None:
    """Until the dump has connected (or ended)."""
    end = time.monotonic() + deadline
    while time.monotonic() < end and proxy.connections == 0 and proc.poll() is None:
        time.sleep(0.002)


def main() -> None:
    args = common.arguments(
        __doc__,
        runs=(int, 96, "dumps to stop (spread evenly over the six ways of stopping)"),
        delay=(float, 0.01, "serve's --delay: seconds before each reply"),
        registers=(int, 4000, "holding registers and coils the device has"),
    )
    rng = random.Random(args.seed)
    report = common.Report("dump kills", args.verbose)
    states = {kind: Counter() for kind in KINDS}
    codes = {kind: Counter() for kind in KINDS}
    saved_nothing = tracebacks = hangs = 0
    with common.scratch("dump") as folder:
        folder = Path(folder)
        data = folder / "device.toml"
        data.write_text(device_data(args.registers, rng))
        with common.serve("--data", data, "--delay", args.delay) as device:
            proxy = common.RecordingProxy((device.host, device.port))
            target = folder / "pump.toml"
            dump = ["dump", target, "-p", proxy.target, "-t", "5"]
            dump += ["--range", f"holding:0-{args.registers - 1}", "--range", f"coils:0-{args.registers - 1}"]
            try:
                # The dump's own length: from its link opening to its end, uninterrupted.
                proxy.take()
                proc = common.popen(*dump, stdout=subprocess.DEVNULL)
                wait_for_link(proxy, proc)
                opened = time.monotonic()
                _, err = proc.communicate(timeout=60)
                length = time.monotonic() - opened
                if proc.returncode != 0 or state_of(target, b"") != "new, complete":
                    common.give_up(f"the uninterrupted dump failed: {err.decode(errors='replace')}")
                # Marked, so that a new dump of the same device is told from it.
                previous = target.read_bytes() + b"# the previous dump\n"
                for index in range(args.runs):
                    kind = list(KINDS)[index % len(KINDS)]
                    target.write_bytes(previous)
                    proxy.take()
                    proc = common.popen(*dump, stdout=subprocess.DEVNULL)
                    wait_for_link(proxy, proc)
                    time.sleep(rng.uniform(0, 1.1 * length))  # now and then after it has ended
                    replies_before = proxy.received
                    signals = KINDS[kind]
                    for number, sig in enumerate(signals):
                        if number:
                            low, high = SECOND_AFTER
                            time.sleep(low * (high / low) ** rng.random())
                        if proc.poll() is None:
                            proc.send_signal(sig)
                    try:
                        _, err = proc.communicate(timeout=END_DEADLINE)
                        code = proc.returncode
                    except subprocess.TimeoutExpired:
                        proc.kill()
                        _, err = proc.communicate()
                        code = None
                    err = err.decode(errors="replace")
                    state = state_of(target, previous)
                    states[kind][state] += 1
                    codes[kind]["hang" if code is None else code] += 1
                    shown = f"{kind} after {'a reply' if replies_before else 'no reply'}: exit {code}, file {state}\n{err[-2000:]}"
                    if code is None:
                        hangs += 1
                        report.fault("hang", shown)
                    if args.verbose:
                        print(shown, flush=True)
                    if "Traceback (most recent call last)" in err:
                        tracebacks += 1
                        report.fault("traceback", shown)
                    if state in ("0 bytes", "partial", "missing"):
                        report.fault("previous dump destroyed", shown)
                    elif signal.SIGKILL not in signals and replies_before and state == "previous kept":
                        saved_nothing += 1
                        report.fault("stopped by SIGINT/SIGTERM, saved nothing", shown)
            finally:
                proxy.close()
    total = Counter()
    for kind in KINDS:
        total.update(states[kind])
        shown = ", ".join(f"{state} {states[kind][state]}" for state in STATES if states[kind][state])
        exits = ", ".join(f"{code}: {n}" for code, n in sorted(codes[kind].items(), key=str))
        report.figure(f"{kind}: runs {sum(states[kind].values())}", f"{shown} (exit {exits})")
    report.figure("an uninterrupted dump", f"{length:.2f} s from its link opening, {len(previous)} bytes")
    report.figure("runs", sum(total.values()))
    report.figure(
        "files valid", total["new, complete"] + total["new, complete = false"] + total["previous kept"]
    )
    report.figure("  new, complete = false", total["new, complete = false"])
    report.figure("  new, complete (finished first)", total["new, complete"])
    report.figure("  previous dump kept", total["previous kept"])
    report.figure("0-byte files (must be 0)", total["0 bytes"])
    report.figure("partial files (must be 0)", total["partial"])
    report.figure(
        "previous dump destroyed (must be 0)", total["0 bytes"] + total["partial"] + total["missing"]
    )
    report.figure("SIGINT/SIGTERM after replies that saved nothing (must be 0)", saved_nothing)
    report.figure("tracebacks (must be 0)", tracebacks)
    report.figure("runs that did not end (must be 0)", hangs)
    report.finish()


if __name__ == "__main__":
    main()
