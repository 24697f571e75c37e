"""Fixtures for mbtool's end-to-end tests.

Peers mbtool talks to in these tests:

* an independent Modbus device: pymodbus's own server, run as a subprocess
  (tests/peers/pymodbus_device.py) on TCP (MBAP or RTU-over-TCP) or on one end of a
  pseudo-terminal pair;
* misbehaving peers in plain Python threads on 127.0.0.1: a silent TCP server, a raw
  responder that answers every request with bytes chosen by the test, and a port that
  refuses connections.

Every wait has a deadline; nothing here can hang the suite.
"""

from __future__ import annotations

import contextlib
import os
import select
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
import tty
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import pytest

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


# ----------------------------------------------------------------------------- helpers


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


@pytest.fixture
def mbtool() -> Callable[..., Result]:
    return run_mbtool


def build_libmodbus(tmp_path_factory, name: str, source: str) -> Path:
    """A C program built with gcc against the system's libmodbus (Debian: libmodbus-dev);
    the test is skipped where gcc or the library is missing."""
    import shutil

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


@pytest.fixture
def pty_pair():
    """A bare pty pair with nothing on the device side (a silent serial line)."""
    pair = PtyPair()
    yield pair
    pair.close()


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


def _stop(proc: subprocess.Popen) -> None:
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
            _stop(proc)
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
        _stop(proc)
        if pty:
            pty.close()
        with contextlib.suppress(OSError):
            os.unlink(errf.name)


@pytest.fixture(scope="session")
def tcp_device():
    """pymodbus over Modbus TCP (MBAP); mbtool target tcp://127.0.0.1:PORT. Units 1 and 2."""
    with start_device(tcp=True, framer="socket") as dev:
        yield dev


@pytest.fixture(scope="session")
def socket_rtu_device():
    """pymodbus speaking RTU framing over a raw TCP socket; mbtool target socket://127.0.0.1:PORT."""
    with start_device(tcp=True, framer="rtu") as dev:
        yield dev


@pytest.fixture(scope="session")
def serial_rtu_device():
    """pymodbus RTU on one end of a pty pair; mbtool target is the other end's path."""
    with start_device(tcp=False, framer="rtu") as dev:
        yield dev


@pytest.fixture(scope="session")
def serial_ascii_device():
    """pymodbus ASCII on one end of a pty pair."""
    with start_device(tcp=False, framer="ascii") as dev:
        yield dev


@pytest.fixture(scope="session")
def holed_device():
    """pymodbus over Modbus TCP with gaps in its address map (pymodbus_device.HOLED): a read
    that touches one answers exception 02. Unit 1."""
    with start_device(tcp=True, framer="socket", units="1", holes=True) as device:
        yield device


NOT_FINITE = """\
[holding_registers]
0 = [0x7FC0, 0x0000, 0x7F80, 0x0000, 0xFF80, 0x0000, 0x41AC, 0x0000]  # NaN, +Inf, -Inf, 21.5
"""

NOT_FINITE_MAP = """\
[device]
type = "float32"
[points.nan]
ref = 40001
[points.inf]
ref = 40003
[points.minus_inf]
ref = 40005
[points.fine]
ref = 40007
"""


@pytest.fixture(scope="session")
def not_finite(tmp_path_factory):
    """mbtool serve with float32 NaN, +Inf, -Inf and 21.5 in holding registers 0-7, and a map."""
    from test_serve import serve

    where = tmp_path_factory.mktemp("not-finite")
    (where / "data.toml").write_text(NOT_FINITE)
    (where / "map.toml").write_text(NOT_FINITE_MAP)
    with serve("--data", str(where / "data.toml")) as server:
        server.map = where / "map.toml"
        yield server


@pytest.fixture(scope="session")
def pki(tmp_path_factory):
    """A CA and the certificates the TLS tests need, made by ``openssl`` into a tmp dir
    (tests/peers/certs.py: with and without the role extension, expired, for another name,
    self-signed, from an unknown CA); never committed keys."""
    import shutil

    from peers.certs import make_pki

    if shutil.which("openssl") is None:
        pytest.skip("the openssl command is not installed (Debian: apt-get install openssl)")
    return make_pki(tmp_path_factory.mktemp("pki"))


@pytest.fixture
def pymodbus_tcp_client(tcp_device):
    """pymodbus's own client on the tcp_device: the independent check of what mbtool wrote."""
    from pymodbus.client import ModbusTcpClient

    client = ModbusTcpClient(tcp_device.host, port=tcp_device.port, timeout=2, retries=1)
    assert client.connect(), "pymodbus client cannot connect to the device"
    yield client
    client.close()


@pytest.fixture
def pymodbus_rtu_socket_client(socket_rtu_device):
    from pymodbus import FramerType
    from pymodbus.client import ModbusTcpClient

    client = ModbusTcpClient(
        socket_rtu_device.host, port=socket_rtu_device.port, framer=FramerType.RTU, timeout=2, retries=1
    )
    assert client.connect()
    yield client
    client.close()


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


@pytest.fixture
def silent_server():
    srv = SilentServer()
    yield srv
    srv.close()


@pytest.fixture
def raw_responder():
    """Factory: raw_responder(reply_bytes_or_callable) -> RawResponder (closed after the test)."""
    made: list[RawResponder] = []

    def make(reply, port: int = 0):
        srv = RawResponder(reply, port)
        made.append(srv)
        return srv

    yield make
    for srv in made:
        srv.close()


@pytest.fixture
def refused_port():
    """A port bound on 127.0.0.1 but not listening: connecting gets ECONNREFUSED."""
    s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    s.bind(("127.0.0.1", 0))
    yield s.getsockname()[1]
    s.close()


def signals_as_from_a_shell() -> None:
    """preexec_fn for a child a test will interrupt: SIGINT and SIGTERM at their defaults and
    unblocked, as a shell starts a command, whatever the test runner's worker did with them
    (a child inherits an ignored signal and the blocked mask across exec)."""
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, signal.SIG_DFL)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT, signal.SIGTERM})


# ----------------------------------------------------------------------------- assertions shared by tests


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
    import re

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


# --- framer event helpers (codec tests) ----------------------------------------------


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
