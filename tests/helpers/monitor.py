"""``mbtool monitor`` on a pty: the frames the tests put on a bus, the line they write them into,
and the monitor started listening and finished.
"""

from __future__ import annotations

import contextlib
import os
import select
import subprocess
import time
import tty

import pytest

from helpers.frames import bad_crc, rtu
from helpers.run import start_mbtool

# What the monitor's tests put on a bus, or in a file of its bytes.
READ_REQ = rtu(bytes.fromhex("11 03 00 6B 00 03"))  # spec §8: unit 17, read 3 registers at 107
READ_RSP = rtu(bytes.fromhex("11 03 06 AE 41 56 52 43 40"))
WRITE_REQ = rtu(bytes.fromhex("01 06 00 01 00 03"))  # its response is an echo
COILS_REQ = rtu(bytes.fromhex("02 01 00 00 00 08"))
INPUT_REQ = rtu(bytes.fromhex("01 04 00 00 00 01"))
EXCEPTION_RSP = rtu(bytes.fromhex("01 84 02"))
DAMAGED_REQ = bad_crc(rtu(bytes.fromhex("01 03 00 00 00 01")))
GARBAGE = bytes.fromhex("FF FF 00")


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
