#!/usr/bin/env python3
"""Instructions a polling transaction costs, counted by valgrind's callgrind: mbtool's client in
process, mbtool's polling command over TCP, and pymodbus's synchronous client over TCP.

Target (issues 30 and 41.9): polling over TCP costs mbtool at most half of pymodbus's
instructions per transaction, with every reply's values new (the headline: a meter's readings
move between polls, so no reply may be decoded or written from the one before).  Callgrind counts the instructions a process runs in user space (the kernel's
side of a system call is not counted); unlike CPU time the count does not move with the
machine's load, so a change's effect shows on a busy machine too.  Each client runs twice,
with a short and a long run of reads of 10 holding registers from unit 1; the difference of
the counts over the difference of reads is one transaction's cost, start-up taken out.  Each
count is the median of ``--repeat`` runs: under valgrind a poll's output, written while its
reply is on its way, sometimes outlasts the client's UNSEEN_WORK and sometimes not, and the
client asks the kernel once more when it does (about 1k instructions a poll from run to run).

* ``mbtool client``: ``link.client.Client`` with the MBAP framer, over a link that answers in
  process at once and makes no system calls: the master's own work a transaction (the frame
  built, the reply framed, judged and decoded), nothing else.
* ``mbtool command``: ``mbtool read-holding-registers 0 10 -p tcp://... --interval 0 --polls N
  -o json`` into a pipe, against libmodbus's C server: all a poll costs, its output included.
* ``pymodbus``: its ``ModbusTcpClient`` reading the same registers from the same server.

By default every reply carries new values (libmodbus's server counts its registers up with
every reply); with ``--same`` the registers keep theirs (a device read faster than its
readings change), where mbtool reuses the decoded reply.  With ``--before DIR`` (a checkout of an
earlier commit, e.g. from ``git worktree add``) mbtool is counted from that tree too.

Needs valgrind; the TCP runs need gcc and libmodbus-dev (as bench/polling_cpu.py), and
``--client-only`` leaves them out.  Run by hand:
    python bench/polling_instructions.py [--short 200] [--long 2200] [--repeat 3] [--same] [--before DIR]
"""

from __future__ import annotations

import argparse
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from polling_cpu import COUNT, PYMODBUS_LOOP, SERVER_C, build, free_port, mbtool_polling

ROOT = Path(__file__).resolve().parent.parent

# The master's own work, with nothing under it: the link answers each request as it is
# written, with the reply libmodbus's server sends (registers 0..9 hold 1000..1009).  Unless
# --same, the replies cycle through many sets of values, so no reply is the one before it.  The replies are made beforehand: the link's own work a read is a slice and a join.
IN_PROCESS = f"""
import sys
sys.path.insert(0, sys.argv.pop(1))  # the tree counted, before the one installed
from mbtool.codec.data_access import ReadHoldingRegisters
from mbtool.codec.framing import make_framer
from mbtool.link.client import Client
from mbtool.link.transport import Transport

COUNT = {COUNT}


class Answering(Transport):
    serial_line = False

    def __init__(self, changing):
        self.replies = []  # each reply after its transaction and protocol ids
        for step in range(64 if changing else 1):
            data = b"".join((1000 + i + step).to_bytes(2, "big") for i in range(COUNT))
            pdu = bytes([3, 2 * COUNT]) + data
            self.replies.append((len(pdu) + 1).to_bytes(2, "big") + bytes([1]) + pdu)
        self.next = 0
        self.reply = b""

    def write(self, adu):
        self.reply = adu[:4] + self.replies[self.next]
        self.next = (self.next + 1) % len(self.replies)

    def read(self, timeout):
        reply, self.reply = self.reply, b""
        return reply


client = Client(Answering(sys.argv[2] == "changing"), make_framer("tcp"))
request = ReadHoldingRegisters(0, COUNT)
for _ in range(int(sys.argv[1])):
    client.execute(1, request)
"""


def instructions(argv: list[str]) -> int:
    """The instructions one run of ``argv`` executes, as callgrind counts them."""
    with tempfile.TemporaryDirectory() as work:
        result = subprocess.run(
            [
                "valgrind",
                "--tool=callgrind",
                f"--callgrind-out-file={work}/out",
                *argv,
            ],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
        )
    if result.returncode:
        sys.exit(f"bench: {' '.join(argv[:4])}... failed under valgrind: {result.stderr[-2000:]}")
    found = re.search(r"Collected : (\d+)", result.stderr)
    if found is None:
        sys.exit(f"bench: no instruction count from callgrind: {result.stderr[-2000:]}")
    return int(found.group(1))


def per_transaction(run, short: int, long: int, repeat: int = 1) -> float:
    """Instructions one transaction costs: ``run(n)`` counts a run of n, start-up included;
    each count is the median of ``repeat`` runs."""

    def count(n: int) -> float:
        return statistics.median(run(n) for _ in range(repeat))

    return (count(long) - count(short)) / (long - short)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--short", type=int, default=200, help="reads in the short run")
    parser.add_argument("--long", type=int, default=2200, help="reads in the long run")
    parser.add_argument(
        "--same",
        action="store_true",
        help="the registers keep their values (by default every reply carries new ones: the headline)",
    )
    parser.add_argument("--changing", action="store_true", help=argparse.SUPPRESS)  # the default now
    parser.add_argument(
        "--repeat",
        type=int,
        default=3,
        help="runs of each length, their median counted (default 3): a poll's work while its reply"
        " is on its way may or may not outlast UNSEEN_WORK under valgrind, which asks the kernel once more",
    )
    parser.add_argument(
        "--before",
        type=Path,
        action="append",
        default=[],
        help="an earlier checkout whose mbtool is counted too (repeatable)",
    )
    parser.add_argument(
        "--client-only", action="store_true", help="count mbtool's client in process only (no TCP, no C)"
    )
    args = parser.parse_args()
    if shutil.which("valgrind") is None:
        sys.exit("bench: valgrind is not installed (apt-get install valgrind)")
    trees = [ROOT] + [tree.resolve() for tree in args.before]
    changing = not args.same
    mode = "changing" if changing else "same"

    for tree in trees:  # compiled first, or the short run would count the compiling
        subprocess.run([sys.executable, "-m", "compileall", "-q", str(tree / "mbtool")], check=True)
    figures: dict[str, float] = {}
    for tree in trees:
        label = "" if tree == ROOT else f" ({tree})"
        figures[f"mbtool client in process{label}"] = per_transaction(
            lambda n, tree=tree: instructions([sys.executable, "-c", IN_PROCESS, str(tree), str(n), mode]),
            args.short,
            args.long,
            args.repeat,
        )
    if not args.client_only:
        with tempfile.TemporaryDirectory() as work:
            server_c = ("#define CHANGING\n" if changing else "") + SERVER_C
            (server_bin,) = build(Path(work), {"server": server_c})
            port = free_port()
            server = subprocess.Popen([str(server_bin), str(port)], stdout=subprocess.PIPE, text=True)
            try:
                if server.stdout.readline().strip() != "READY":
                    sys.exit("bench: libmodbus's server did not start")
                launcher = "import sys; sys.path.insert(0, sys.argv.pop(1)); from mbtool.cli import main; sys.exit(main())"
                for tree in trees:
                    label = "" if tree == ROOT else f" ({tree})"
                    figures[f"mbtool command over TCP{label}"] = per_transaction(
                        lambda n, tree=tree: instructions(
                            [sys.executable, "-c", launcher, str(tree), *mbtool_polling(port, n)]
                        ),
                        args.short,
                        args.long,
                        args.repeat,
                    )
                figures["pymodbus client over TCP"] = per_transaction(
                    lambda n: instructions([sys.executable, "-c", PYMODBUS_LOOP, str(port), str(n)]),
                    args.short,
                    args.long,
                    args.repeat,
                )
            finally:
                server.terminate()
                server.wait(timeout=5)
    print(
        f"instructions a transaction (callgrind), {args.long} - {args.short} reads of {COUNT} registers,"
        f" {'values new every read' if changing else 'values that stay (--same)'}"
    )
    for label, count in figures.items():
        print(f"{label:<50} {count / 1000:8.1f} k")
    pymodbus = figures.get("pymodbus client over TCP")
    if pymodbus:
        for label, count in figures.items():
            if label.startswith("mbtool command over TCP"):
                target = " (target <= 0.5)" if label == "mbtool command over TCP" else ""
                print(f"{label}: {count / pymodbus:.2f} x pymodbus's client{target}")


if __name__ == "__main__":
    main()
