"""The helpers every test shares: running mbtool (a process, or in this process), the peers it
talks to (pymodbus's device, pseudo-terminal pairs, misbehaving loopback servers, ``mbtool
serve`` and ``mbtool bridge`` as a user runs them), frames written independently of mbtool,
fakes for the unit tests, and the assertions the tests have in common.

Test files import them as ``from helpers import ...`` (pyproject's ``pythonpath = ["tests"]``);
tests/conftest.py holds the fixtures built on them.  Every wait has a deadline.
"""

from __future__ import annotations

import contextlib
import gc
import io
import json
import os
import re
import select
import shutil
import signal
import socket
import struct
import subprocess
import sys
import tempfile
import threading
import time
import tty
import urllib.error
import urllib.request
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from mbtool.cli import main
from mbtool.codec.errors import ModbusException
from mbtool.codec.pdu import ExceptionResponse
from mbtool.link.transport import Transport

TESTS_DIR = Path(__file__).resolve().parent
REPO_ROOT = TESTS_DIR.parent
DEVICE_SCRIPT = TESTS_DIR / "peers" / "pymodbus_device.py"

# Linux pseudo-terminals (kernel 6.x, as here) may refuse PARENB and CS7 with EINVAL (whether
# they do depends on the settings the pty had before), so every mbtool run on a pty passes
# these (mbtool's default parity is E): a pty has no parity to set anyway.
PTY_SERIAL_OPTS = ("--parity", "N")

READY_DEADLINE = 20.0  # seconds for the pymodbus device to start listening
MBTOOL_TIMEOUT = 20.0  # seconds for any single mbtool invocation

# The data the pymodbus device serves (see tests/peers/pymodbus_device.py)
HOLDING = [100 + i for i in range(20)]
INPUT = [200 + i for i in range(20)]
COILS = [i % 2 == 0 for i in range(20)]
DISCRETE = [True] * 20

# ----------------------------------------------------------------------------- frames and ports


def free_port() -> int:
    """A TCP port on 127.0.0.1 nobody listens on right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def free_udp_port() -> int:
    """A UDP port on 127.0.0.1 nobody listens on right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def crc16(data: bytes) -> bytes:
    """Modbus RTU CRC-16 (poly 0xA001, init 0xFFFF), low byte first. Independent of mbtool."""
    crc = 0xFFFF
    for b in data:
        crc ^= b
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return bytes([crc & 0xFF, crc >> 8])


def lrc(data: bytes) -> int:
    return (-sum(data)) & 0xFF


def rtu(frame_wo_crc: bytes) -> bytes:
    return frame_wo_crc + crc16(frame_wo_crc)


def mbap(tid: int, unit: int, pdu: bytes) -> bytes:
    """An MBAP ADU: transaction id, protocol 0, length, unit, PDU (spec: Modbus/TCP, MBAP header)."""
    return struct.pack(">HHHB", tid, 0, len(pdu) + 1, unit) + pdu


def read_mbap(sock: socket.socket) -> tuple[int, int, bytes]:
    """(transaction id, unit, PDU) of one MBAP ADU read from ``sock``."""
    header = _read_exactly(sock, 7)
    tid, _, length, unit = struct.unpack(">HHHB", header)
    return tid, unit, _read_exactly(sock, length - 1)


def _read_exactly(sock: socket.socket, size: int) -> bytes:
    data = b""
    while len(data) < size:
        chunk = sock.recv(size - len(data))
        assert chunk, "the peer closed the connection"
        data += chunk
    return data


def ascii_frame(unit: int, pdu: bytes) -> bytes:
    """A Modbus ASCII frame: ':', the unit, PDU and LRC in hex, CR LF."""
    body = bytes([unit]) + pdu
    return b":" + (body + bytes([lrc(body)])).hex().upper().encode() + b"\r\n"


def bad_crc(frame: bytes) -> bytes:
    """An RTU frame with its CRC's last byte spoilt."""
    return frame[:-1] + bytes([frame[-1] ^ 0xFF])


# ----------------------------------------------------------------------------- running mbtool


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


def run_mbtool(
    *args: str, timeout: float = MBTOOL_TIMEOUT, env: dict[str, str] | None = None, input: str | None = None
) -> Result:
    """Run the real CLI as a subprocess: python -m mbtool ARGS (stdout/stderr are pipes)."""
    argv = [str(a) for a in args]
    t0 = time.monotonic()
    try:
        cp = subprocess.run(
            [sys.executable, "-m", "mbtool", *argv],
            cwd=REPO_ROOT,
            env=mbtool_env(env),
            capture_output=True,
            text=True,
            timeout=timeout,
            input=input,
            stdin=None if input is not None else subprocess.DEVNULL,
        )
    except subprocess.TimeoutExpired as exc:
        out = exc.stdout.decode() if isinstance(exc.stdout, bytes) else (exc.stdout or "")
        err = exc.stderr.decode() if isinstance(exc.stderr, bytes) else (exc.stderr or "")
        pytest.fail(
            f"mbtool {' '.join(argv)} did not finish within {timeout}s\nstdout:\n{out}\nstderr:\n{err}"
        )
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


# ----------------------------------------------------------------------------- assertions and waits


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


def assert_one_error_line(res: Result, code: int) -> str:
    """Exit code as expected, exactly one 'mbtool: ' line on stderr, no traceback. Returns the line."""
    assert res.returncode == code, str(res)
    assert "Traceback" not in res.stderr, str(res)
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1, f"expected exactly one stderr line\n{res}"
    assert lines[0].startswith("mbtool: "), str(res)
    return lines[0]


@dataclass
class HexLine:
    direction: str  # TX or RX
    data: bytes
    verdict: str  # the rest of the line after the hex pairs
    raw: str = field(repr=False, default="")


def parse_hex_lines(stderr: str) -> list[HexLine]:
    """Parse --hex trace lines: 'TX 01 03 ... C5 CD  CRC C5 CD ok'."""
    out = []
    for ln in stderr.splitlines():
        m = re.match(r"^(TX|RX) ((?:[0-9A-F]{2} )*[0-9A-F]{2})(.*)$", ln)
        if m:
            out.append(HexLine(m.group(1), bytes.fromhex(m.group(2)), m.group(3).strip(), ln))
    return out


def plain_pairs(res: Result) -> list[tuple[int, str]]:
    """Plain output 'ADDRESS VALUE' lines as (address, value-text) pairs."""
    pairs = []
    for ln in res.lines:
        parts = ln.split()
        assert len(parts) == 2, f"plain line is not 'ADDRESS VALUE': {ln!r}\n{res}"
        pairs.append((int(parts[0]), parts[1]))
    return pairs


def expect_ok(res: Result) -> Result:
    assert res.returncode == 0, str(res)
    assert "Traceback" not in res.stderr, str(res)
    return res


def wait_until(predicate, deadline: float, step: float = 0.05) -> bool:
    """Whether ``predicate()`` came true within ``deadline`` seconds."""
    end = time.monotonic() + deadline
    while time.monotonic() < end:
        if predicate():
            return True
        time.sleep(step)
    return predicate()


def closed_by_peer(sock: socket.socket, wait: float = 0.0) -> bool:
    """Has the server closed this socket (EOF or reset)?  Reads and discards what is pending."""
    end = time.monotonic() + wait
    while True:
        ready, _, _ = select.select([sock], [], [], max(0.0, end - time.monotonic()))
        if not ready:
            return False
        try:
            if not sock.recv(65536):
                return True
        except (ConnectionResetError, BrokenPipeError):
            return True
        except (BlockingIOError, TimeoutError):
            pass
        if time.monotonic() >= end:
            return False


# ----------------------------------------------------------------------------- pty pair


class PtyPair:
    """Two pseudo-terminal pairs joined by a relay thread: a virtual null-modem cable.

    The device opens ``device_path``, mbtool opens ``mbtool_path``.  Bytes written on one
    end come out of the other.  The relay records everything that goes through, so a test
    can assert that nothing was sent.  With ``echo=True`` every byte mbtool sends is also
    copied back to mbtool first (an RS-485 adapter that hears itself).
    """

    def __init__(self, echo: bool = False) -> None:
        self.echo = echo
        self._dev_master, self._dev_slave = os.openpty()
        self._mb_master, self._mb_slave = os.openpty()
        for fd in (self._dev_master, self._dev_slave, self._mb_master, self._mb_slave):
            tty.setraw(fd)
        self.device_path = os.ttyname(self._dev_slave)
        self.mbtool_path = os.ttyname(self._mb_slave)
        self.to_device = bytearray()  # bytes mbtool sent towards the device
        self.to_mbtool = bytearray()  # bytes the device sent towards mbtool
        # Everything that crossed, in order: (monotonic time, "request" or "reply", bytes).
        self.crossings: list[tuple[float, str, bytes]] = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._relay, name="pty-relay", daemon=True)
        self._thread.start()

    def _relay(self) -> None:
        # We keep our own slave fds open so the masters never see EIO when a peer closes.
        fds = [self._dev_master, self._mb_master]
        while not self._stop.is_set():
            try:
                ready, _, _ = select.select(fds, [], [], 0.05)
            except (OSError, ValueError):
                return
            for fd in ready:
                try:
                    data = os.read(fd, 4096)
                except OSError:
                    continue
                if not data:
                    continue
                with self._lock:
                    self.crossings.append(
                        (time.monotonic(), "request" if fd == self._mb_master else "reply", data)
                    )
                    if fd == self._mb_master:
                        self.to_device += data
                        if self.echo:
                            os.write(self._mb_master, data)
                        os.write(self._dev_master, data)
                    else:
                        self.to_mbtool += data
                        os.write(self._mb_master, data)

    def sent_by_mbtool(self, settle: float = 0.1) -> bytes:
        time.sleep(settle)
        with self._lock:
            return bytes(self.to_device)

    def clear(self) -> None:
        with self._lock:
            self.to_device.clear()
            self.to_mbtool.clear()
            self.crossings.clear()

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2)
        for fd in (self._dev_master, self._dev_slave, self._mb_master, self._mb_slave):
            with contextlib.suppress(OSError):
                os.close(fd)


# ----------------------------------------------------------------------------- pymodbus device


@dataclass
class Device:
    target: str  # what mbtool gets as -p
    framer: str  # socket | rtu | ascii
    proc: subprocess.Popen
    host: str | None = None
    port: int | None = None
    pty: PtyPair | None = None
    stderr_path: str | None = None
    units: tuple[int, ...] = (1,)

    def log(self) -> str:
        if self.stderr_path and os.path.exists(self.stderr_path):
            return Path(self.stderr_path).read_text(errors="replace")[-4000:]
        return ""


def _wait_ready(proc: subprocess.Popen, deadline: float) -> None:
    assert proc.stdout is not None
    buf = b""
    end = time.monotonic() + deadline
    fd = proc.stdout.fileno()
    while time.monotonic() < end:
        r, _, _ = select.select([fd], [], [], 0.1)
        if r:
            chunk = os.read(fd, 1024)
            if not chunk:  # EOF: the device died
                break
            buf += chunk
            if b"READY" in buf:
                return
        elif proc.poll() is not None:
            break
    raise RuntimeError(f"pymodbus device did not become READY (exit={proc.poll()}, stdout={buf!r})")


def stop_device(proc: subprocess.Popen) -> None:
    """Stop a pymodbus device (SIGTERM, then SIGKILL after 3 s)."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=3)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=3)
    if proc.stdout:
        proc.stdout.close()


@contextlib.contextmanager
def start_device(
    *,
    tcp: bool,
    framer: str,
    units: str = "1,2",
    pty_echo: bool = False,
    holes: bool = False,
    port: int | None = None,
    tls: tuple[str, ...] = (),
    udp: bool = False,
):
    """Start tests/peers/pymodbus_device.py; yield a Device; always stop it.

    ``holes``: the device's address map has gaps (pymodbus_device.HOLED); ``port``: the TCP
    port to listen on (a free one by default), e.g. to bring a stopped device back; ``tls``:
    Modbus/TCP Security, with these arguments (--cert S --key K [--ca CA]), target tls://;
    ``udp``: datagrams, target udp:// (``framer`` socket) or rtu+udp:// (rtu)."""
    errf = tempfile.NamedTemporaryFile(prefix="mbtool-device-", suffix=".log", delete=False)
    pty = None
    if tls:
        port = port or free_port()
        where = ["--tls", f"127.0.0.1:{port}", *tls]
    elif udp:
        port = port or free_udp_port()
        where = ["--udp", f"127.0.0.1:{port}"]
    elif tcp:
        port = port or free_port()
        where = ["--tcp", f"127.0.0.1:{port}"]
    else:
        pty = PtyPair(echo=pty_echo)
        where = ["--serial", pty.device_path]
    proc = subprocess.Popen(
        [
            sys.executable,
            str(DEVICE_SCRIPT),
            *where,
            "--framer",
            framer,
            "--units",
            units,
            *(["--holes"] if holes else []),
        ],
        stdout=subprocess.PIPE,
        stderr=errf,
        stdin=subprocess.DEVNULL,
        cwd=REPO_ROOT,
    )
    errf.close()
    try:
        try:
            _wait_ready(proc, READY_DEADLINE)
        except RuntimeError as exc:
            stop_device(proc)
            raise RuntimeError(
                f"{exc}\ndevice stderr:\n{Path(errf.name).read_text(errors='replace')[-3000:]}"
            ) from None
        if tcp or tls or udp:
            if tls:
                scheme = "tls"
            elif udp:
                scheme = "udp" if framer == "socket" else "rtu+udp"
            else:
                scheme = "tcp" if framer == "socket" else "socket"
            dev = Device(
                f"{scheme}://127.0.0.1:{port}",
                framer,
                proc,
                host="127.0.0.1",
                port=port,
                stderr_path=errf.name,
                units=tuple(int(u) for u in units.split(",")),
            )
        else:
            dev = Device(
                pty.mbtool_path,
                framer,
                proc,
                pty=pty,
                stderr_path=errf.name,
                units=tuple(int(u) for u in units.split(",")),
            )
        yield dev
    finally:
        stop_device(proc)
        if pty:
            pty.close()
        with contextlib.suppress(OSError):
            os.unlink(errf.name)


def build_libmodbus(tmp_path_factory, name: str, source: str) -> Path:
    """A C program built with gcc against the system's libmodbus (Debian: libmodbus-dev);
    the test is skipped where gcc or the library is missing."""

    gcc = shutil.which("gcc")
    if gcc is None:
        pytest.skip("gcc is not installed: the libmodbus peer cannot be built")
    include = next(
        (p for p in (Path("/usr/include/modbus"), Path("/usr/local/include/modbus")) if p.is_dir()), None
    )
    if include is None:
        pytest.skip("libmodbus headers are not installed (Debian: apt-get install libmodbus-dev)")
    where = tmp_path_factory.mktemp("libmodbus")
    (where / f"{name}.c").write_text(source)
    build = subprocess.run(
        [gcc, "-o", str(where / name), str(where / f"{name}.c"), f"-I{include}", "-lmodbus"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    if build.returncode != 0:
        pytest.skip(f"the libmodbus peer does not build here: {build.stderr.strip()[-300:]}")
    return where / name


# ----------------------------------------------------------------------------- misbehaving peers

CLOSE = object()  # what a RawResponder's reply function returns to close the connection instead


class _ThreadServer:
    """A TCP listener on 127.0.0.1 handled in a thread; records every byte received."""

    def __init__(self, port: int = 0) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.sock.bind(("127.0.0.1", port))
        self.sock.listen(8)
        self.sock.settimeout(0.05)
        self.port = self.sock.getsockname()[1]
        self.received = bytearray()
        self.requests: list[bytes] = []  # one entry per recv() chunk
        self.connections = 0
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._conns: list[socket.socket] = []
        self._thread = threading.Thread(target=self._serve, daemon=True)
        self._thread.start()

    def answer(self, request: bytes) -> bytes | None:  # override
        return None

    def _serve(self) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = self.sock.accept()
            except TimeoutError:
                pass
            except OSError:
                return
            else:
                conn.setblocking(False)
                with self._lock:
                    self.connections += 1
                    self._conns.append(conn)
            conns = list(self._conns)
            if not conns:
                continue
            try:
                r, _, _ = select.select(conns, [], [], 0.02)
            except (OSError, ValueError):
                r = []
            for c in r:
                try:
                    data = c.recv(4096)
                except OSError:
                    data = b""
                if not data:
                    with self._lock:
                        self._conns.remove(c)
                    c.close()
                    continue
                with self._lock:
                    self.received += data
                    self.requests.append(bytes(data))
                reply = self.answer(bytes(data))
                if reply is CLOSE:  # the peer hangs up instead of answering
                    with self._lock:
                        self._conns.remove(c)
                    c.close()
                    continue
                if reply:
                    with contextlib.suppress(OSError):
                        c.sendall(reply)

    def received_bytes(self, settle: float = 0.1) -> bytes:
        time.sleep(settle)
        with self._lock:
            return bytes(self.received)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2)
        for c in self._conns:
            with contextlib.suppress(OSError):
                c.close()
        self.sock.close()


class SilentServer(_ThreadServer):
    """Accepts connections, reads everything, never answers."""

    @property
    def tcp_target(self) -> str:
        return f"tcp://127.0.0.1:{self.port}"

    @property
    def socket_target(self) -> str:
        return f"socket://127.0.0.1:{self.port}"


class RawResponder(SilentServer):
    """Answers every request with ``reply`` (bytes, or a function of the request bytes)."""

    def __init__(self, reply: bytes | Callable[[bytes], bytes], port: int = 0) -> None:
        self.reply = reply
        super().__init__(port)

    def answer(self, request: bytes) -> bytes | None:
        return self.reply(request) if callable(self.reply) else self.reply


# ----------------------------------------------------------------------------- mbtool serve and bridge

SERVE_READY = 10.0  # seconds for serve or bridge to say where it listens
PROMPT = 2.0  # a reply from serve under abuse; generous, since other test runs share the cores


def host_and_port(where: str) -> tuple[str, int]:
    """The host and port of a network target serve or bridge listens on (("", 0) for a serial line)."""
    if where.startswith(("tcp://", "tls://", "udp://", "rtu+udp://")):
        host, _, port = where.split("://", 1)[1].rpartition(":")
        return host, int(port)
    return "", 0


class Served:
    """A running ``mbtool serve``: where it listens (``target``, ``host``, ``port``), its log
    (stdout) and stderr as written so far, its memory, raw connections to it."""

    def __init__(self, proc: subprocess.Popen, log_path: Path, err_path: Path, first_line: str) -> None:
        self.proc = proc
        self.log_path = log_path
        self.err_path = err_path
        self.first_line = first_line
        where = self.target = first_line.split()[1]
        self.host, self.port = host_and_port(where)
        self.result: tuple[int, str, str] | None = None

    @property
    def socket_target(self) -> str:
        return f"socket://{self.host}:{self.port}"

    def log(self) -> str:
        """Its stdout: the serving line, then (without -q) a line a frame."""
        if self.result is not None:
            return self.first_line + "\n" + self.result[1]
        return self.log_path.read_text(errors="replace")

    def rss_kb(self) -> int:
        for line in Path(f"/proc/{self.proc.pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
        raise AssertionError("no VmRSS for the server")

    def alive(self) -> bool:
        return self.proc.poll() is None

    def connect(self, **kw) -> socket.socket:
        sock = socket.create_connection((self.host, self.port), timeout=PROMPT, **kw)
        sock.settimeout(PROMPT)
        return sock

    def stop(self, sig: int = signal.SIGTERM) -> tuple[int, str, str]:
        """(exit code, stdout after the serving line, stderr) once it has stopped."""
        if self.result is None:
            code = stop_serve(self.proc, sig)
            log = self.log_path.read_text(errors="replace")
            self.result = (code, log.partition("\n")[2], self.err_path.read_text(errors="replace"))
        return self.result


def start_serve(args: list[str], folder: Path, quiet: bool = True) -> tuple[subprocess.Popen, Path, Path]:
    """``mbtool serve ARGS`` started, its stdout and stderr going to files in ``folder`` (not
    pipes a busy test might not drain, which would stall the server's log and look like the
    very blocking some tests look for): (process, stdout's file, stderr's file)."""
    log_path = folder / f"serve-{time.monotonic_ns()}.out"
    err_path = log_path.with_suffix(".err")
    with open(log_path, "wb") as out, open(err_path, "wb") as err:
        proc = start_mbtool("serve", *(["-q"] if quiet else []), *args, stdout=out, stderr=err)
    return proc, log_path, err_path


def serving_line(proc: subprocess.Popen, log_path: Path) -> str | None:
    """The "serving ..." line, or None if the server exited (or said nothing) first."""
    end = time.monotonic() + SERVE_READY
    while time.monotonic() < end:
        text = log_path.read_text(errors="replace")
        if "\n" in text:
            return text.split("\n")[0]
        if proc.poll() is not None:
            return None
        time.sleep(0.02)
    return None


def stop_serve(proc: subprocess.Popen, sig: int = signal.SIGTERM) -> int:
    if proc.poll() is None:
        proc.send_signal(sig)
    try:
        return proc.wait(timeout=5)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait(timeout=5)
        return -9


@contextlib.contextmanager
def serve(*args: str, target: str = "tcp://127.0.0.1:0", quiet: bool = True):
    """A running ``mbtool serve -p TARGET ARGS`` (``-q`` unless ``quiet`` is False); stopped with
    SIGTERM at the end, which must end it with exit 0 and no traceback.  A test may stop it
    itself first (``server.stop(signal.SIGINT)``)."""
    with tempfile.TemporaryDirectory(prefix="mbtool-serve-") as folder:
        proc, log_path, err_path = start_serve(["-p", target, *args], Path(folder), quiet)
        server = None
        try:
            line = serving_line(proc, log_path)
            assert line and line.startswith("serving "), (
                f"mbtool serve did not start: {log_path.read_text()!r} {err_path.read_text()!r}"
            )
            server = Served(proc, log_path, err_path, line)
            yield server
            if server.result is None:
                assert server.alive(), f"the server died: {err_path.read_text()}"
        finally:
            if server is not None:
                code, _, err = server.stop()
            else:
                code, err = stop_serve(proc), err_path.read_text(errors="replace")
        assert "Traceback" not in err, err
        assert code == 0, f"serve exited {code}: {err}"


class Bridge:
    def __init__(self, proc: subprocess.Popen, first_line: str, out_path: str) -> None:
        self.proc = proc
        self.first_line = first_line  # "bridging tcp://127.0.0.1:PORT (tcp) to ... "
        self.out_path = out_path
        where = self.listening = first_line.split()[1]
        self.host, self.port = host_and_port(where)
        self.result: tuple[int, str, str] | None = None

    @property
    def target(self) -> str:
        return f"tcp://{self.host}:{self.port}"

    def output(self) -> str:
        with open(self.out_path, encoding="utf-8") as out:
            return out.read()

    def records(self) -> list[dict]:
        """The JSON records, once the bridge has stopped: a transaction is printed after its
        reply has gone, so a client's reply does not mean its record is out yet."""
        _, out, _ = self.stop()
        return [json.loads(line) for line in out.splitlines()]

    def stop(self, sig: int = signal.SIGTERM) -> tuple[int, str, str]:
        """(exit code, stdout, stderr) once it has stopped."""
        if self.result is None:
            if self.proc.poll() is None:
                self.proc.send_signal(sig)
            try:
                _, err = self.proc.communicate(timeout=15)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                _, err = self.proc.communicate(timeout=5)
            self.result = (self.proc.returncode, self.output(), self.first_line + "\n" + err)
        return self.result


@contextlib.contextmanager
def bridge(*args: str, listen: str = "tcp://127.0.0.1:0", fmt: str = "json"):
    """A running ``mbtool bridge``; its stdout goes to a file (a pipe nobody reads would fill).

    Its timeout is 2 s unless ``args`` say otherwise (a busy test machine can keep pymodbus's
    device from answering in 1 s); a client through it waits longer than that.
    """
    out = tempfile.NamedTemporaryFile(prefix="mbtool-bridge-", suffix=".out", delete=False)
    shape = [] if "-q" in args else ["-o", fmt]  # -q shows no transaction to shape
    proc = start_mbtool("bridge", "--listen", listen, *shape, "-t", "2", *args, stdout=out)
    out.close()
    running = None
    try:
        running = Bridge(proc, first_line(proc, "bridging ", proc.stderr), out.name)
        yield running
    finally:
        if running is not None:
            code, _, err = running.stop()
            assert code == 0, f"bridge exited {code}: {err}"
            assert "Traceback" not in err, err
        elif proc.poll() is None:
            proc.kill()
            proc.communicate(timeout=5)
        os.unlink(out.name)


def pymodbus_tcp(peer: Served | Bridge, framer: str = "tcp", timeout: float = PROMPT):
    """pymodbus's client, connected to a serve or a bridge over TCP with ``framer`` (tcp, rtu or
    ascii): the independent master.  No retries: a test sees every failure."""
    from pymodbus import FramerType  # pymodbus loads only for the tests that use it
    from pymodbus.client import ModbusTcpClient

    kind = {"tcp": FramerType.SOCKET, "rtu": FramerType.RTU, "ascii": FramerType.ASCII}[framer]
    client = ModbusTcpClient(peer.host, port=peer.port, framer=kind, timeout=timeout, retries=0)
    assert client.connect()
    return client


def timed_read(client, address: int = 7) -> float:
    """One FC03 read checked against the demo data (register N holds N); seconds it took."""
    t0 = time.monotonic()
    response = client.read_holding_registers(address, count=1)
    elapsed = time.monotonic() - t0
    assert not response.isError(), response
    assert response.registers == [address]
    return elapsed


# ----------------------------------------------------------------------------- the exporter

METER_DATA = REPO_ROOT / "examples" / "energy-meter-data.toml"
METER_MAP = REPO_ROOT / "examples" / "energy-meter.toml"


@dataclass
class Running:
    proc: subprocess.Popen
    url: str  # http://127.0.0.1:PORT
    line: str  # the first line it printed
    stderr: Path

    def get(self, path: str, headers: dict[str, str] | None = None, timeout: float = 30.0):
        return http_get(self.url + path, headers, timeout)


@contextlib.contextmanager
def exporting(*args: str, tmp_path: Path):
    """mbtool exporter ARGS on a free loopback port; stopped by SIGTERM, which must end it with
    exit 0 and no traceback."""
    stderr = tmp_path / f"exporter-{len(list(tmp_path.glob('exporter-*')))}.err"
    with open(stderr, "w") as err:
        proc = start_mbtool("exporter", "--listen", "127.0.0.1:0", *args, stderr=err, text=False)
    try:
        line = first_line(proc, "exporting on ")
        yield Running(proc, re.search(r"http://[^ ]+", line)[0], line, stderr)
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
        try:
            proc.communicate(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.communicate(timeout=5)
            pytest.fail("the exporter did not stop on SIGTERM within 10 s")
        assert proc.returncode == 0, stderr.read_text()
        assert "Traceback" not in stderr.read_text()


def http_get(url: str, headers: dict[str, str] | None = None, timeout: float = 30.0) -> tuple[int, str, str]:
    """(status, content type, body) of a GET, whatever the status."""
    opener = urllib.request.build_opener(urllib.request.ProxyHandler({}))  # loopback, never a proxy
    try:
        with opener.open(urllib.request.Request(url, headers=headers or {}), timeout=timeout) as response:
            return response.status, response.headers["Content-Type"], response.read().decode()
    except urllib.error.HTTPError as error:
        return error.code, error.headers["Content-Type"], error.read().decode()


# ----------------------------------------------------------------------------- a bus's frames (monitor)

# What the monitor's tests put on a bus, or in a file of its bytes.
READ_REQ = rtu(bytes.fromhex("11 03 00 6B 00 03"))  # spec §8: unit 17, read 3 registers at 107
READ_RSP = rtu(bytes.fromhex("11 03 06 AE 41 56 52 43 40"))
WRITE_REQ = rtu(bytes.fromhex("01 06 00 01 00 03"))  # its response is an echo
COILS_REQ = rtu(bytes.fromhex("02 01 00 00 00 08"))
INPUT_REQ = rtu(bytes.fromhex("01 04 00 00 00 01"))
EXCEPTION_RSP = rtu(bytes.fromhex("01 84 02"))
DAMAGED_REQ = bad_crc(rtu(bytes.fromhex("01 03 00 00 00 01")))
GARBAGE = bytes.fromhex("FF FF 00")


# ----------------------------------------------------------------------------- mbtool monitor on a pty

MONITOR_DEADLINE = 20.0  # seconds for any one monitor run


class Line:
    """One pty pair: the test writes the bus traffic into the master, mbtool listens on the slave."""

    def __init__(self) -> None:
        self.master, self.slave = os.openpty()
        tty.setraw(self.master)
        tty.setraw(self.slave)  # no echo: anything readable on the master was written by mbtool
        self.path = os.ttyname(self.slave)

    def send(self, *frames: bytes) -> None:
        os.write(self.master, b"".join(frames))

    def written_by_monitor(self) -> bytes:
        data = b""
        while select.select([self.master], [], [], 0.2)[0]:
            chunk = os.read(self.master, 4096)
            if not chunk:
                break
            data += chunk
        return data

    def close(self) -> None:
        for fd in (self.master, self.slave):
            with contextlib.suppress(OSError):
                os.close(fd)


def start_monitor(*args: str, env: dict | None = None) -> subprocess.Popen:
    """The CLI, started and listening (it says so on stderr): only then are bytes sent."""
    proc = start_mbtool("monitor", *args, env=env, text=False)
    seen = b""
    end = time.monotonic() + MONITOR_DEADLINE
    while not seen.endswith(b"nothing is sent\n"):
        if time.monotonic() > end or proc.poll() is not None:
            proc.kill()
            out, err = proc.communicate(timeout=5)
            pytest.fail(f"monitor did not start listening: {seen + err!r}")
        if select.select([proc.stderr], [], [], 0.1)[0]:
            seen += os.read(proc.stderr.fileno(), 4096)
    proc.listening = seen.decode()
    return proc


def finish(proc: subprocess.Popen) -> tuple[int, str, str]:
    """(exit code, stdout, stderr) of a monitor started by ``start_monitor``, once it ends."""
    try:
        out, err = proc.communicate(timeout=MONITOR_DEADLINE)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, err = proc.communicate(timeout=5)
        pytest.fail(f"monitor did not stop within {MONITOR_DEADLINE}s\n{out.decode()}\n{err.decode()}")
    return proc.returncode, out.decode(), proc.listening + err.decode()


def json_lines(stdout: str) -> list[dict]:
    return [json.loads(line) for line in stdout.splitlines() if line.strip()]


# ----------------------------------------------------------------------------- fakes for unit tests


class FakeClock:
    """A monotonic clock that moves only when slept on (or when a fake link waits)."""

    def __init__(self) -> None:
        self.now = 100.0
        self.sleeps: list[float] = []

    def __call__(self) -> float:
        return self.now

    def sleep(self, seconds: float) -> None:
        self.sleeps.append(seconds)
        self.now += seconds


class ScriptedLink(Transport):
    """Answers each request with the next scripted list of chunks; time passes on silence."""

    def __init__(self, clock: FakeClock, replies: list[list[bytes]], serial_line: bool = True) -> None:
        self.clock = clock
        self.replies = replies
        self.serial_line = serial_line
        self.written: list[bytes] = []
        self.pending: list[bytes] = []

    def write(self, data: bytes) -> None:
        self.written.append(data)
        self.pending = list(self.replies.pop(0)) if self.replies else []

    def read(self, timeout: float) -> bytes:
        if self.pending:
            return self.pending.pop(0)
        self.clock.now += timeout
        return b""


def device_executor(device, requests: list):
    """An ``execute`` (as a map read takes) answered by a simulated device's unit 1 in-process,
    every request recorded in ``requests``; an exception reply raises as the client's does."""

    def execute(request):
        requests.append(request)
        reply = request.decode_response(device.handle(1, request.encode()))
        if isinstance(reply, ExceptionResponse):
            raise ModbusException(reply.function_code, reply.exception_code)
        return reply

    return execute


# ----------------------------------------------------------------------------- framer events (codec tests)


def drain_events(framer) -> list:
    """Every event the framer has now."""
    events = []
    while (event := framer.next_event()) is not None:
        events.append(event)
    return events


def settle_events(framer) -> list:
    """next_event until it has nothing, then silence until it has nothing; nothing may stay buffered."""
    events = drain_events(framer)
    for _ in range(2000):
        event = framer.silence()
        if event is None:
            break
        events.append(event)
    assert framer.buffered == 0
    return events


def promtool_check(text: str) -> None:
    """Prometheus's own checker on an exposition (``promtool check metrics``: the parse and
    the lint); skips the test when Debian's prometheus, which ships promtool, is missing."""
    promtool = shutil.which("promtool")
    if promtool is None:
        pytest.skip("promtool is not installed (Debian's prometheus ships it)")
    check = subprocess.run(
        [promtool, "check", "metrics"], input=text, capture_output=True, text=True, timeout=MBTOOL_TIMEOUT
    )
    assert check.returncode == 0, (check.stdout + check.stderr, text)


def expositions(stream: str) -> list[str]:
    """A stream of whole expositions (poll -o prom, a round each) cut into them: each starts
    with modbus_up's HELP line."""
    head = "# HELP modbus_up "
    return [head + part for part in stream.split(head)[1:]]
