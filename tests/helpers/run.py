"""Running mbtool as a user runs it: a process (``run_mbtool``, ``start_mbtool``), or in this
process (``run_cli``), and the first line a long-running one prints.
"""

from __future__ import annotations

import contextlib
import gc
import io
import os
import select
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import pytest

from mbtool.cli import main

TESTS_DIR = Path(__file__).resolve().parent.parent  # tests/, above this package
REPO_ROOT = TESTS_DIR.parent
MBTOOL_TIMEOUT = 20.0  # seconds for any single mbtool invocation


@dataclass
class Result:
    args: list[str]
    returncode: int
    stdout: str
    stderr: str
    elapsed: float

    @property
    def lines(self) -> list[str]:
        return [ln for ln in self.stdout.splitlines() if ln.strip()]

    def __str__(self) -> str:  # shown in assertion messages
        return (
            f"$ mbtool {' '.join(self.args)}\n-> exit {self.returncode} in {self.elapsed:.2f}s\n"
            f"--- stdout ---\n{self.stdout}--- stderr ---\n{self.stderr}"
        )


def mbtool_env(extra: dict[str, str] | None = None) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("MBTOOL_")}
    env["PYTHONPATH"] = str(REPO_ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    env.setdefault("PYTHONDONTWRITEBYTECODE", "1")
    env["NO_COLOR"] = "1"
    env["COLUMNS"] = "200"
    if extra:
        env.update(extra)
    return env


STREAMS = ("stdin", "stdout", "stderr")  # their files, where a run is given a folder for them


def run_mbtool(
    *args: str,
    timeout: float = MBTOOL_TIMEOUT,
    env: dict[str, str] | None = None,
    input: str | None = None,
    files: Path | None = None,
) -> Result:
    """Run the real CLI as a subprocess: python -m mbtool ARGS (stdout/stderr are pipes).  With
    ``files``, a folder, stdin (``input``), stdout and stderr are files in it instead: for
    megabytes in or out, which through pipes wake this process for every line mbtool flushes."""
    argv = [str(a) for a in args]
    t0 = time.monotonic()
    with contextlib.ExitStack() as opened:
        if files is None:
            streams = {"capture_output": True, "input": input}
            streams["stdin"] = None if input is not None else subprocess.DEVNULL
        else:
            (files / "stdin").write_text(input or "")
            streams = {
                name: opened.enter_context(open(files / name, "r" if name == "stdin" else "w"))
                for name in STREAMS
            }
        try:
            cp = subprocess.run(
                [sys.executable, "-m", "mbtool", *argv],
                cwd=REPO_ROOT,
                env=mbtool_env(env),
                text=True,
                timeout=timeout,
                **streams,
            )
        except subprocess.TimeoutExpired as exc:
            out = exc.stdout.decode() if isinstance(exc.stdout, bytes) else (exc.stdout or "")
            err = exc.stderr.decode() if isinstance(exc.stderr, bytes) else (exc.stderr or "")
            pytest.fail(
                f"mbtool {' '.join(argv)} did not finish within {timeout}s\nstdout:\n{out}\nstderr:\n{err}"
            )
    if files is not None:
        cp.stdout, cp.stderr = ((files / name).read_text() for name in STREAMS[1:])
    return Result(argv, cp.returncode, cp.stdout, cp.stderr, time.monotonic() - t0)


# Signals a run may set a handler for (main: SIGTERM; check: SIGTERM, SIGHUP and SIGINT, ignored
# once its line is out; dump: SIGINT and SIGTERM): put back after an in-process run, so neither
# this test process nor a child it starts later inherits them.
_RUN_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


def start_mbtool(*args: str, env: dict[str, str] | None = None, **popen) -> subprocess.Popen:
    """``python -m mbtool ARGS`` started and left running, as a shell starts it (its signals at
    their defaults), stdin empty, stdout and stderr text pipes unless ``popen`` says otherwise."""
    options = {
        "cwd": REPO_ROOT,
        "env": mbtool_env(env),
        "preexec_fn": signals_as_from_a_shell,
        "stdin": subprocess.DEVNULL,
        "stdout": subprocess.PIPE,
        "stderr": subprocess.PIPE,
        "text": True,
    }
    return subprocess.Popen([sys.executable, "-m", "mbtool", *map(str, args)], **{**options, **popen})


def run_cli(*args: str, env: dict[str, str] | None = None) -> Result:
    """Run the CLI in this process: ``mbtool.cli.main(ARGS)``, as ``run_mbtool`` runs it in a
    process of its own, and the same result: the exit code ``main`` leaves with, stdout and
    stderr as written (neither a terminal), stdin empty, the environment of ``mbtool_env`` and
    the repository as the working directory.

    For what needs no process of its own (argument errors, dry runs, the offline commands,
    sim://, a map or profile that cannot be loaded).  Not for signals, terminals, stdin, a
    stdout closed or full, or timing: those need ``run_mbtool``.  What ``main`` changes in the
    process (the signal handlers, the collector's frozen objects) is put back."""
    argv = [str(a) for a in args]
    out, err = io.BytesIO(), io.BytesIO()
    streams = (sys.stdin, sys.stdout, sys.stderr)
    handlers = {sig: signal.getsignal(sig) for sig in _RUN_SIGNALS}
    environ = dict(os.environ)
    os.environ.clear()
    os.environ.update(mbtool_env(env))
    # Held here as well as in sys: a wrapper dropped by sys would close its buffer with it.
    captured = (
        io.TextIOWrapper(io.BytesIO(), encoding="utf-8"),
        io.TextIOWrapper(out, encoding="utf-8"),
        io.TextIOWrapper(err, encoding="utf-8", errors="backslashreplace", line_buffering=True),
    )
    sys.stdin, sys.stdout, sys.stderr = captured
    t0 = time.monotonic()
    try:
        with contextlib.chdir(REPO_ROOT):
            main(argv)
        code = 0
    except SystemExit as done:
        code = 0 if done.code is None else done.code if isinstance(done.code, int) else 1
    finally:
        elapsed = time.monotonic() - t0
        for stream in captured[1:]:
            with contextlib.suppress(ValueError, OSError):
                stream.flush()
        sys.stdin, sys.stdout, sys.stderr = streams
        os.environ.clear()
        os.environ.update(environ)
        for sig, handler in handlers.items():
            signal.signal(sig, handler)
        gc.unfreeze()  # main froze what start-up built, for a run that ends with its process
    return Result(argv, code, _text(out.getvalue()), _text(err.getvalue()), elapsed)


def _text(data: bytes) -> str:
    """What ``subprocess.run(..., text=True)`` makes of a stream: UTF-8, universal newlines."""
    return data.decode("utf-8").replace("\r\n", "\n").replace("\r", "\n")


def signals_as_from_a_shell() -> None:
    """preexec_fn for a child a test will interrupt: SIGINT and SIGTERM at their defaults and
    unblocked, as a shell starts a command, whatever the test runner's worker did with them
    (a child inherits an ignored signal and the blocked mask across exec)."""
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, signal.SIG_DFL)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT, signal.SIGTERM})


def interrupt_after(args, wait_lines: int, sig=signal.SIGTERM) -> tuple[int, str, str]:
    """Run mbtool ARGS, wait for ``wait_lines`` lines of its stdout (or a second, for none),
    send ``sig``: (exit code, stdout, stderr)."""
    proc = start_mbtool(*args)
    got = [proc.stdout.readline() for _ in range(wait_lines)]
    if not wait_lines:
        time.sleep(1.0)  # past start-up, into the wait before the first slot
    proc.send_signal(sig)
    out, err = proc.communicate(timeout=10)
    return proc.returncode, "".join(got) + out, err


def first_line(proc: subprocess.Popen, starts: str, stream=None, wait: float = 10.0) -> str:
    """The first line a long-running mbtool prints (``serving ...``, ``bridging ...``), read
    from ``stream`` (its stdout by default) within ``wait`` seconds; the process is killed
    and the test fails with its stderr if the line is not ``starts...``."""
    fd = (stream or proc.stdout).fileno()
    end = time.monotonic() + wait
    buf = b""
    while time.monotonic() < end and b"\n" not in buf:
        ready, _, _ = select.select([fd], [], [], 0.1)
        if ready:
            chunk = os.read(fd, 4096)
            if not chunk:
                break
            buf += chunk
    if not buf.startswith(starts.encode()):
        proc.kill()
        _, err = proc.communicate(timeout=5)
        raise RuntimeError(f"mbtool did not start: {buf!r} {err}")
    return buf.split(b"\n")[0].decode()
