"""Pseudo-terminals as serial lines: a pair joined by a relay thread (a null-modem cable that
records what crossed, or an RS-485 adapter that hears itself), and the settings a pty takes.
"""

from __future__ import annotations

import contextlib
import os
import select
import threading
import time
import tty

# Linux pseudo-terminals (kernel 6.x, as here) may refuse PARENB and CS7 with EINVAL (whether
# they do depends on the settings the pty had before), so every mbtool run on a pty passes
# these (mbtool's default parity is E): a pty has no parity to set anyway.
PTY_SERIAL_OPTS = ("--parity", "N")


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
