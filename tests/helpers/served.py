"""``mbtool serve`` and ``mbtool bridge`` run as a user runs them, each stopped by SIGTERM and
required to end cleanly, and pymodbus's client as the independent master in front of them.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import socket
import subprocess
import tempfile
import time
from pathlib import Path

from helpers.run import first_line, start_mbtool

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
