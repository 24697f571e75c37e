#!/usr/bin/env python3
"""CPU a polling transaction costs the master, beside libmodbus's C client, a bare Python
loop and pymodbus's synchronous client, all against libmodbus's C server.

Target (issue: fast where it counts): reading 10 holding registers back to back over
TCP loopback, mbtool's user + system CPU per transaction at most 1.4 x libmodbus's C
client's.  The server is libmodbus's own (C, faster than any client here), so the
figures are the clients' own; a bare Python socket loop is the ceiling a Python
client can reach (its cost is nearly all system calls).

Each client runs as its own process twice, with a short and a long run of reads; the
difference of their CPU (os.wait4's rusage) divided by the difference of reads is the
cost of one transaction with start-up taken out.  Clients run in alternating rounds on
one core, the server on the other; the medians are printed with transactions a second
(reads over wall time of the long run, start-up included, so a lower bound), and the
targets are figured round by round (mbtool beside the C client and the bare loop of the
same round) and their median printed.

mbtool runs as the real command: ``--interval 0 --polls N -o json`` into a pipe, each
poll written and flushed as documented.

Needs gcc and Debian's libmodbus-dev (headers and library); says so and exits where
either is missing.  Run by hand:  python bench/polling_cpu.py [--rounds 5]
"""

from __future__ import annotations

import argparse
import os
import shutil
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
COUNT = 10  # holding registers per read

# libmodbus's own TCP server, shared with the tests' peers.
SERVER_C = (ROOT / "tests" / "peers" / "libmodbus_server.c").read_text()

# libmodbus's client: NEW_CONTEXT opens the link from the first arguments; the last is the
# number of reads of 10 holding registers from unit 1.
CLIENT_C = r"""
#include <stdio.h>
#include <stdlib.h>
#include <modbus.h>

int main(int argc, char **argv) {
    modbus_t *ctx = NEW_CONTEXT;
    long n = atol(argv[argc - 1]);
    uint16_t regs[10];
    modbus_set_slave(ctx, 1);
    if (modbus_connect(ctx) < 0) { perror("connect"); return 1; }
    for (long i = 0; i < n; i++)
        if (modbus_read_registers(ctx, 0, 10, regs) != 10) { perror("read"); return 1; }
    modbus_close(ctx);
    modbus_free(ctx);
    return 0;
}
"""
TCP_CLIENT_C = CLIENT_C.replace("NEW_CONTEXT", 'modbus_new_tcp("127.0.0.1", atoi(argv[1]))')

BARE_LOOP = """
import socket, struct, sys
sock = socket.create_connection(("127.0.0.1", int(sys.argv[1])))
sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
for tid in range(int(sys.argv[2])):
    sock.sendall(struct.pack(">HHHBBHH", tid & 0xFFFF, 0, 6, 1, 3, 0, 10))
    sock.recv(256)
"""

PYMODBUS_LOOP = """
import sys
from pymodbus.client import ModbusTcpClient
client = ModbusTcpClient("127.0.0.1", port=int(sys.argv[1]))
client.connect()
for _ in range(int(sys.argv[2])):
    reply = client.read_holding_registers(0, count=10, device_id=1)
    if reply.isError():
        sys.exit(f"pymodbus: {reply}")
"""

# Two cores or more: the server gets one, the client under test another.
PINNED = len(os.sched_getaffinity(0)) >= 2


def on_core(core: int):
    return (lambda: os.sched_setaffinity(0, {core})) if PINNED else None


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def build(workdir: Path, sources: dict[str, str]) -> list[Path]:
    """Programs against libmodbus, compiled here from C ``sources`` by name; exits saying
    why where they cannot be (no gcc, no libmodbus-dev)."""
    gcc = shutil.which("gcc")
    if gcc is None:
        sys.exit("bench: gcc is not installed (apt-get install gcc libmodbus-dev)")
    flags = subprocess.run(["pkg-config", "--cflags", "--libs", "libmodbus"], capture_output=True, text=True)
    cflags = flags.stdout.split() if flags.returncode == 0 else ["-I/usr/include/modbus", "-lmodbus"]
    built = []
    for name, source in sources.items():
        (workdir / f"{name}.c").write_text(source)
        result = subprocess.run(
            [gcc, "-O2", "-o", str(workdir / name), str(workdir / f"{name}.c"), *cflags],
            capture_output=True,
            text=True,
        )
        if result.returncode:
            sys.exit(
                f"bench: cannot build libmodbus's {name} (apt-get install libmodbus-dev): {result.stderr}"
            )
        built.append(workdir / name)
    return built


def cpu_of(argv: list[str], stdout=subprocess.DEVNULL) -> tuple[float, float]:
    """(user + system CPU seconds, wall seconds) of one run of ``argv`` on the client core."""
    start = time.perf_counter()
    proc = subprocess.Popen(argv, stdout=stdout, stderr=subprocess.PIPE, preexec_fn=on_core(1))
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - start
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode:
        sys.exit(f"bench: {' '.join(argv[:4])}... failed: {proc.stderr.read().decode()}")
    return usage.ru_utime + usage.ru_stime, wall


def mbtool_polling(port: int, n: int) -> list[str]:
    """mbtool's arguments for n polls of the registers the clients read, back to back, as JSON."""
    return [
        "read-holding-registers",
        "0",
        str(COUNT),
        "-p",
        f"tcp://127.0.0.1:{port}",
        "--interval",
        "0",
        "--polls",
        str(n),
        "-o",
        "json",
    ]


def clients(client_c: Path, port: int) -> dict[str, callable]:
    env_python = [sys.executable, "-c"]

    def mbtool(n: int) -> list[str]:
        return [sys.executable, "-m", "mbtool", *mbtool_polling(port, n)]

    return {
        "libmodbus C": lambda n: [str(client_c), str(port), str(n)],
        "bare Python loop": lambda n: [*env_python, BARE_LOOP, str(port), str(n)],
        "pymodbus sync": lambda n: [*env_python, PYMODBUS_LOOP, str(port), str(n)],
        "mbtool": mbtool,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--short", type=int, default=1000, help="reads in the short run")
    parser.add_argument("--long", type=int, default=20000, help="reads in the long run")
    parser.add_argument(
        "--same",
        action="store_true",
        help="the server's registers keep their values, as in a device whose readings change slower"
        " than it is polled (by default they count up after every reply, so every poll's values are new)",
    )
    parser.add_argument("--changing", action="store_true", help=argparse.SUPPRESS)  # the default now
    args = parser.parse_args()
    os.chdir(ROOT)
    changing = not args.same
    server_c = ("#define CHANGING\n" if changing else "") + SERVER_C
    with tempfile.TemporaryDirectory() as work:
        server_bin, client_bin = build(Path(work), {"server": server_c, "client": TCP_CLIENT_C})
        port = free_port()
        server = subprocess.Popen(
            [str(server_bin), str(port)], stdout=subprocess.PIPE, text=True, preexec_fn=on_core(0)
        )
        try:
            if server.stdout.readline().strip() != "READY":
                sys.exit("bench: libmodbus's server did not start")
            runs = clients(client_bin, port)
            per_tx: dict[str, list[float]] = {name: [] for name in runs}
            rates: dict[str, list[float]] = {name: [] for name in runs}
            for round_number in range(args.rounds):
                names = list(runs)
                if round_number % 2:
                    names.reverse()  # alternate who goes first: a noisy stretch hurts all alike
                for name in names:
                    short_cpu, _ = cpu_of(runs[name](args.short))
                    long_cpu, long_wall = cpu_of(runs[name](args.long))
                    per_tx[name].append((long_cpu - short_cpu) / (args.long - args.short) * 1e6)
                    rates[name].append(args.long / long_wall)
        finally:
            server.terminate()
            server.wait(timeout=5)
    base = statistics.median(per_tx["libmodbus C"])
    print(
        f"{args.rounds} rounds, {args.long} - {args.short} reads of {COUNT} registers, TCP loopback,"
        f" libmodbus's C server{', values new every read' if changing else ', values that stay (--same)'}"
        f"{'; server and clients on separate cores' if PINNED else ''}"
    )
    print(f"{'client':<18} {'CPU us/tx':>10} {'x C':>6} {'tx/s':>8}   (per round: us/tx)")
    for name in runs:
        cost = statistics.median(per_tx[name])
        rounds = " ".join(f"{value:.1f}" for value in per_tx[name])
        print(
            f"{name:<18} {cost:>10.1f} {cost / base:>6.2f} {statistics.median(rates[name]):>8.0f}   ({rounds})"
        )
    # The targets, paired by round: a round's clients run within seconds of each other, so a
    # slow stretch of the machine (system calls here cost 25-33 us from one minute to the
    # next) moves them alike, where the medians above may come from different stretches.
    ratios = [m / c for m, c in zip(per_tx["mbtool"], per_tx["libmodbus C"], strict=True)]
    above = [m - b for m, b in zip(per_tx["mbtool"], per_tx["bare Python loop"], strict=True)]
    print(
        f"mbtool, the median of the rounds: {statistics.median(ratios):.2f} x libmodbus's C client"
        f" (target <= 1.4); {statistics.median(above):.1f} us of Python a poll above the bare loop"
        " (target <= 10)"
    )


if __name__ == "__main__":
    main()
