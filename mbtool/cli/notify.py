"""systemd's notification protocol (sd_notify(3)), with the standard library: a run under a
``Type=notify`` unit says READY=1 once it is serving, feeds the watchdog (WATCHDOG=1) at half
the ``WatchdogSec`` systemd asked for, and says STOPPING=1 on its way out.

systemd names its socket in NOTIFY_SOCKET (a path, or ``@name`` in the abstract namespace)
and the watchdog's period in WATCHDOG_USEC (for the process WATCHDOG_PID names, when it is
set).  Each message is one datagram.  Outside systemd nothing is sent; a socket that has gone
is never a failure of the run: the poller polls on.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import socket


def systemd_notifier(environ=os.environ) -> Notifier | None:
    """The run's notifier under systemd (NOTIFY_SOCKET set); None outside it, where a run makes
    nothing for it (not even its lock: the plant's threads are counted to the byte under a
    ulimit, tests/e2e/test_poll.py)."""
    address = environ.get("NOTIFY_SOCKET", "")
    return Notifier(address, environ) if address else None


class Notifier:
    """The run's messages to systemd."""

    def __init__(self, address: str, environ) -> None:
        self.address = "\0" + address[1:] if address.startswith("@") else address
        self.period: float | None = None  # seconds between watchdog pings
        usec, pid = environ.get("WATCHDOG_USEC", ""), environ.get("WATCHDOG_PID", "")
        if usec.isdigit() and int(usec) > 0 and (not pid or pid == str(os.getpid())):
            self.period = int(usec) / 2e6
        self.stopped = threading.Event()
        self.lock = threading.Lock()  # no ping after STOPPING=1, nor on a closed socket
        self.sock: socket.socket | None = None  # made at the first message

    def send(self, message: str) -> None:
        import socket  # noqa: PLC0415 - socket, 2-4 ms: under systemd only

        try:
            if self.sock is None:
                self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
            self.sock.sendto(message.encode(), self.address)  # the one socket a run sends on
        except OSError:
            pass  # systemd gone or the socket unreachable: nothing a poller can do about it

    def ready(self, status: str = "", moved: Callable[[], bool] | None = None) -> None:
        """READY=1 (and a STATUS line), then the watchdog's pings from a thread of their own:
        each only when ``moved()`` says the work moved since the last (a plant's
        ``Plant.moved``), so that systemd restarts a run that is alive but stuck; with no
        ``moved``, while the process lives."""
        self.send("READY=1" + (f"\nSTATUS={status}" if status else ""))
        if self.period is not None:
            threading.Thread(target=self._feed, args=(moved,), name="watchdog", daemon=True).start()

    def _feed(self, moved: Callable[[], bool] | None) -> None:
        while not self.stopped.wait(self.period):
            if moved is not None and not moved():
                continue  # stuck: no ping, and systemd's WatchdogSec runs out
            with self.lock:
                if not self.stopped.is_set():
                    self.send("WATCHDOG=1")

    def stopping(self) -> None:
        with self.lock:
            self.stopped.set()
            self.send("STOPPING=1")
            if self.sock is not None:
                self.sock.close()
                self.sock = None
