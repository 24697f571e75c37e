"""What the campaigns share: running an mbtool checkout, a ``serve`` to talk to, a recording
proxy that says whether anything was sent, the RSS of a process, and the report.

The peers the tests already have (tests/helpers/: the pseudo-terminal pair that records
what crosses it, the environment mbtool runs in, the signal set-up of a child a test
interrupts) are imported from there, not copied.
"""

from __future__ import annotations

import argparse
import contextlib
import re
import select
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import NoReturn

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "tests"))

from helpers.ptys import PTY_SERIAL_OPTS, PtyPair  # noqa: E402
from helpers.run import first_line, mbtool_env, signals_as_from_a_shell  # noqa: E402

__all__ = ["PTY_SERIAL_OPTS", "PtyPair"]  # for the campaigns, from tests/helpers/ptys.py

TREE = ROOT  # the checkout whose mbtool runs (--mbtool DIR)
RUN_DEADLINE = 30.0  # seconds any one mbtool run may take before it counts as a hang


def arguments(doc: str, **sizes: tuple[type, object, str]) -> argparse.Namespace:
    """The campaign's options: its sizes (name=(type, default, help)), --seed and --mbtool."""
    parser = argparse.ArgumentParser(description=doc.strip().splitlines()[0], epilog="See README.md here.")
    for name, (kind, default, text) in sizes.items():
        parser.add_argument(f"--{name.replace('_', '-')}", type=kind, default=default, help=text)
    parser.add_argument("--seed", type=int, default=1, help="random seed: the same seed, the same campaign")
    parser.add_argument(
        "--mbtool",
        type=Path,
        default=ROOT,
        metavar="DIR",
        help="run the mbtool of this checkout (a git worktree of another commit), default: this one",
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="print each fault as it is found")
    args = parser.parse_args()
    global TREE
    TREE = args.mbtool.resolve()
    if not (TREE / "mbtool" / "__init__.py").is_file():
        parser.error(f"--mbtool {args.mbtool}: no mbtool package there")
    sys.path.insert(0, str(TREE))  # in-process checks (the map loader) use the same mbtool
    return args


def give_up(why: str) -> NoReturn:
    """The campaign could not be set up (no fault found, none ruled out): exit 2."""
    print(f"campaign: {why}", file=sys.stderr)
    sys.exit(2)


def env(extra: dict[str, str] | None = None) -> dict[str, str]:
    """The tests' environment for mbtool, pointed at TREE; MBTOOL_DEBUG=1 so that a bug shows
    as a Python traceback, which the campaigns count."""
    return mbtool_env({"PYTHONPATH": str(TREE), "MBTOOL_DEBUG": "1", **(extra or {})})


def argv(*args: object) -> list[str]:
    return [sys.executable, "-m", "mbtool", *(str(a) for a in args)]


def popen(*args: object, extra_env: dict[str, str] | None = None, **kw) -> subprocess.Popen:
    """mbtool ARGS started as a shell starts a command (SIGINT and SIGTERM at their defaults;
    a ``preexec_fn`` given does that itself, with whatever else it sets)."""
    kw.setdefault("stdin", subprocess.DEVNULL)
    kw.setdefault("stdout", subprocess.PIPE)
    kw.setdefault("stderr", subprocess.PIPE)
    kw.setdefault("preexec_fn", signals_as_from_a_shell)
    return subprocess.Popen(argv(*args), cwd=TREE, env=env(extra_env), **kw)


class Run:
    def __init__(self, args: list[str], code: int | None, out: str, err: str, elapsed: float) -> None:
        self.args, self.code, self.out, self.err, self.elapsed = args, code, out, err, elapsed

    @property
    def hung(self) -> bool:
        return self.code is None

    @property
    def traceback(self) -> bool:
        return "Traceback (most recent call last)" in self.err

    def __str__(self) -> str:
        return f"$ mbtool {' '.join(self.args)}\n-> exit {self.code}\n{self.out[-1500:]}{self.err[-3000:]}"


def run(*args: object, deadline: float = RUN_DEADLINE, extra_env: dict[str, str] | None = None, **kw) -> Run:
    """mbtool ARGS to its end; a run past the deadline is killed and reported with code None.
    ``kw`` goes to popen (a ``preexec_fn`` that caps the run's address space, say)."""
    began = time.monotonic()
    proc = popen(*args, extra_env=extra_env, **kw)
    try:
        out, err = proc.communicate(timeout=deadline)
        code = proc.returncode
    except subprocess.TimeoutExpired:
        proc.kill()
        out, err = proc.communicate()
        code = None
    return Run(
        [str(a) for a in args],
        code,
        out.decode(errors="replace"),
        err.decode(errors="replace"),
        time.monotonic() - began,
    )


def first_stream_line(proc: subprocess.Popen, stream, starts: str, wait: float = 20.0) -> str:
    """The first line a long-running mbtool prints on ``stream`` (a pipe of the process), as
    the tests read it; a campaign gives up with the reason when it does not come."""
    try:
        return first_line(proc, starts, stream, wait)
    except RuntimeError as failed:
        give_up(str(failed))


def stop(proc: subprocess.Popen, wait: float = 10.0) -> int | None:
    """SIGTERM, then SIGKILL past ``wait``: the exit code."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(wait)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)
    return proc.returncode


class Served:
    """A running ``mbtool serve``: where it listens."""

    def __init__(self, proc: subprocess.Popen, line: str) -> None:
        self.proc = proc
        found = re.search(r"tcp://([\d.]+):(\d+)", line)
        self.host, self.port = (found[1], int(found[2])) if found else ("", 0)
        self.target = f"tcp://{self.host}:{self.port}" if found else ""


@contextlib.contextmanager
def serve(*args: object, target: str = "tcp://127.0.0.1:0"):
    """``mbtool serve -q`` on ``target`` for the duration; stopped with SIGTERM after."""
    proc = popen("serve", "-q", "-p", target, *args, stderr=subprocess.DEVNULL)
    try:
        yield Served(proc, first_stream_line(proc, proc.stdout, "serving "))
    finally:
        stop(proc)
        proc.stdout.close()


class RecordingProxy:
    """A TCP listener on loopback relaying to ``upstream`` (host, port) both ways, counting the
    connections made to it and the bytes clients sent and received: the witness that a
    command sent nothing.  One thread, a select loop; ``settle`` waits for two full turns of
    it, so a connection or byte the kernel holds for it when asked is counted."""

    def __init__(self, upstream: tuple[str, int] | None) -> None:
        self.upstream = upstream
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.listener.setblocking(False)
        self.port = self.listener.getsockname()[1]
        self.target = f"tcp://127.0.0.1:{self.port}"
        self.connections = 0
        self.sent = 0  # bytes clients sent
        self.received = 0  # bytes clients were sent back
        self._peer: dict[socket.socket, socket.socket | None] = {}  # client -> upstream, and back
        self._clients: set[socket.socket] = set()
        self._turns = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="recording-proxy", daemon=True)
        self._thread.start()

    def _loop(self) -> None:
        while not self._stop.is_set():
            ready, _, _ = select.select([self.listener, *self._peer], [], [], 0.01)
            for sock in ready:
                if sock is self.listener:
                    self._accept()
                else:
                    self._relay(sock)
            self._turns += 1

    def _accept(self) -> None:
        while True:
            try:
                client, _ = self.listener.accept()
            except BlockingIOError:
                return
            self.connections += 1
            upstream = None
            if self.upstream is not None:
                try:
                    upstream = socket.create_connection(self.upstream, timeout=5)
                except OSError:
                    upstream = None
            self._clients.add(client)
            self._peer[client] = upstream
            if upstream is not None:
                self._peer[upstream] = client

    def _relay(self, sock: socket.socket) -> None:
        try:
            data = sock.recv(65536)
        except OSError:
            data = b""
        other = self._peer.get(sock)
        if not data:
            self._close(sock)
            return
        if sock in self._clients:
            self.sent += len(data)
        else:
            self.received += len(data)
        if other is not None:
            try:
                other.sendall(data)
            except OSError:
                self._close(sock)

    def _close(self, sock: socket.socket) -> None:
        other = self._peer.pop(sock, None)
        self._clients.discard(sock)
        sock.close()
        if other is not None:
            self._peer.pop(other, None)
            self._clients.discard(other)
            other.close()

    def settle(self) -> None:
        turns = self._turns
        end = time.monotonic() + 5
        while self._turns < turns + 2 and time.monotonic() < end:
            time.sleep(0.005)

    def take(self) -> tuple[int, int, int]:
        """(connections, bytes sent, bytes received) since the last take."""
        self.settle()
        counts = (self.connections, self.sent, self.received)
        self.connections = self.sent = self.received = 0
        return counts

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2)
        for sock in list(self._peer):
            with contextlib.suppress(OSError):
                sock.close()
        self.listener.close()


def rss_kb(pid: int) -> int | None:
    """The resident set size of a process (VmRSS in /proc/PID/status), KiB; None once gone."""
    try:
        with open(f"/proc/{pid}/status") as status:
            for line in status:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1])
    except OSError:
        return None
    return None


def scratch(prefix: str) -> tempfile.TemporaryDirectory:
    return tempfile.TemporaryDirectory(prefix=f"mbtool-campaign-{prefix}-")


class Report:
    """The figures, in the order added, and the faults: printed at the end, exit 1 on a fault."""

    def __init__(self, name: str, verbose: bool = False) -> None:
        self.name = name
        self.verbose = verbose
        self.figures: list[tuple[str, object]] = []
        self.faults: dict[str, int] = {}
        self.examples: dict[str, str] = {}

    def figure(self, label: str, value: object) -> None:
        self.figures.append((label, value))

    def fault(self, kind: str, example: str = "") -> None:
        """A fault of ``kind``; the first example of each kind is printed with the summary."""
        self.faults[kind] = self.faults.get(kind, 0) + 1
        if example and kind not in self.examples:
            self.examples[kind] = example
        if self.verbose:
            print(f"FAULT {kind}: {example}", file=sys.stderr, flush=True)

    def finish(self) -> None:
        width = max((len(label) for label, _ in self.figures), default=0)
        print(f"== {self.name} (mbtool of {TREE})")
        for label, value in self.figures:
            print(f"{label:<{width}}  {value}")
        if not self.faults:
            print("faults: none")
            sys.exit(0)
        print("faults: " + ", ".join(f"{kind} {count}" for kind, count in self.faults.items()))
        for kind, example in self.examples.items():
            print(f"--- first {kind}:\n{example.rstrip()}")
        sys.exit(1)
