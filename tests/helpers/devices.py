"""Independent Modbus devices: pymodbus's server as a subprocess (tests/peers/pymodbus_device.py)
on TCP, TLS, UDP or a pty, the data it serves, and a libmodbus peer built with gcc.
"""

from __future__ import annotations

import contextlib
import os
import select
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import pytest

from helpers.ptys import PtyPair
from helpers.run import REPO_ROOT, TESTS_DIR
from helpers.sockets import free_port, free_udp_port

DEVICE_SCRIPT = TESTS_DIR / "peers" / "pymodbus_device.py"

READY_DEADLINE = 20.0  # seconds for the pymodbus device to start listening

# The data the pymodbus device serves (see tests/peers/pymodbus_device.py)
HOLDING = [100 + i for i in range(20)]
INPUT = [200 + i for i in range(20)]
COILS = [i % 2 == 0 for i in range(20)]
DISCRETE = [True] * 20


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
