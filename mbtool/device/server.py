"""The server behind ``mbtool serve`` and ``mbtool bridge``: a TCP, TLS or UDP port, or a serial line.

``Server`` is what the commands use: it picks the transport from the target, once, and
stops cleanly on Ctrl-C and SIGTERM.  What a server does whatever the transport (who
answers, the I/O layer's faults, the stats, the loop) is ``mbtool.device.serving``'s; each
transport's loop is its own module: ``mbtool.device.tcp_server`` (many clients, none able
to hold the others up), ``mbtool.device.tls_server`` (the same inside TLS, Modbus/TCP
Security, with its clients' roles), ``mbtool.device.udp_server`` (a datagram a request)
and ``mbtool.device.serial_server`` (a slave on a line).
"""

from __future__ import annotations

import contextlib
import random
import signal
from collections.abc import Callable, Iterator
from typing import TYPE_CHECKING, Any

from mbtool.device.device import Device
from mbtool.device.serial_server import SerialServer
from mbtool.device.serving import Answerer, IoFaults, Responder, ServerParts, Serving, Stats
from mbtool.device.tcp_server import FIRST_REQUEST_TIMEOUT, IDLE_TIMEOUT, MAX_CLIENTS, TcpServer
from mbtool.device.udp_server import UdpServer
from mbtool.errors import STOP_SIGNALS, UsageError
from mbtool.link import IN_PROCESS
from mbtool.link.transport import SerialSettings, Target
from mbtool.link.transport import parse_target as parse_link_target

if TYPE_CHECKING:
    import ssl


def parse_target(text: str) -> Target:
    """tcp://, tls://, udp:// or rtu+udp://HOST[:PORT] (PORT 0: any free port), or a serial
    device path / pyserial URL."""
    target = parse_link_target(text, listening=True)
    if target.scheme in IN_PROCESS:
        raise UsageError(f"{target} is the in-process device; serve on tcp://HOST:PORT or a serial port")
    return target


class Server:
    """Runs until ``stop()`` (called from a signal handler) or a fatal error on the port.

    ``device`` answers, or ``answerer`` (a gateway's forwarder) where it is None.  On TCP,
    ``queued`` answers take a bus's time, one at a time (``bridge``), and ``max_clients``,
    ``idle_timeout`` and ``first_request_timeout`` bound the clients; on UDP ``udp_rate`` caps
    the datagrams answered a second for one source; on a serial line, ``settings`` are the line's."""

    def __init__(
        self,
        device: Device | None,
        target: Target,
        framer_name: str,
        *,
        answerer: Answerer | None = None,
        queued: bool = False,
        faults: IoFaults | None = None,
        seed: int | None = None,
        settings: SerialSettings | None = None,
        log: Callable[[str, str, bytes, str], None] | None = None,
        max_clients: int = MAX_CLIENTS,
        idle_timeout: float | None = IDLE_TIMEOUT,
        first_request_timeout: float | None = FIRST_REQUEST_TIMEOUT,
        tls_context: ssl.SSLContext | None = None,
        write_roles: frozenset[str] | None = None,
        udp_rate: float | None = None,
    ) -> None:
        faults = faults or IoFaults()
        self.stats = Stats()
        log = log or (lambda direction, peer, data, note: None)
        if answerer is None:
            assert device is not None, "a server answers with its device, or its answerer"
            answerer = Responder(device, faults, self.stats, random.Random(seed), log)
        self.port: Serving
        limits: dict[str, Any] = {
            "queued": queued,
            "max_clients": max_clients,
            "idle_timeout": idle_timeout,
            "first_request_timeout": first_request_timeout,
        }
        parts = ServerParts(target, framer_name, answerer, faults, self.stats, log)
        if target.scheme == "tcp":
            self.port = TcpServer(parts, **limits)
        elif target.scheme == "tls":
            from mbtool.device.tls_server import TlsServer  # noqa: PLC0415 - ssl, 6 ms: tls:// only

            assert tls_context is not None, (
                "a tls:// server needs its context (mbtool.link.tls.server_context)"
            )
            self.port = TlsServer(parts, context=tls_context, write_roles=write_roles, **limits)
        elif target.scheme in ("udp", "rtu+udp"):
            self.port = UdpServer(parts, udp_rate)
        else:
            self.port = SerialServer(parts, settings or SerialSettings())

    def open(self) -> None:
        """Bind the port or open the serial line; ConnectionFailed (exit 6) if it cannot be."""
        self.port.open()

    def run(self, tick: Callable[[], None] | None = None) -> None:
        """Serve until stopped; ``tick`` is called after every turn of the loop (at most TICK apart)."""
        self.port.run(tick)

    def stop(self) -> None:
        self.port.stop()

    @contextlib.contextmanager
    def stopped_by_signals(self) -> Iterator[None]:
        """Inside, Ctrl-C, SIGTERM and SIGHUP stop the server cleanly (the loop ends, clients are closed)
        instead of interrupting it; the handlers before come back afterwards."""
        previous = {
            sig: signal.signal(sig, lambda signum, frame: self.stop())
            for sig in STOP_SIGNALS
            if signal.getsignal(sig) is not signal.SIG_IGN
        }
        try:
            yield
        finally:
            for sig, handler in previous.items():
                signal.signal(sig, handler)
