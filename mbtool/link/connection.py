"""A connection as the options describe it, checked, and a Client opened over it."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from contextlib import ExitStack, contextmanager
from typing import TYPE_CHECKING

from mbtool.codec.errors import RequestError
from mbtool.codec.record import record

if TYPE_CHECKING:
    from mbtool.codec.framer import Framer
    from mbtool.link.client import Client, Trace


@record
class Connection:
    """Built from keywords: what -p, -u and the line options say about the link."""

    port: str | None = None
    unit: int = 1
    framer: str | None = None  # None: tcp for tcp://, rtu for everything else
    baud: int = 19200
    parity: str = "E"
    bytesize: int = 8
    stopbits: int = 1
    timeout: float = 1.0
    retries: int = 0
    echo: bool = False  # a half-duplex adapter echoes every byte sent
    rs485: bool = False  # drive RTS for the direction of a two-wire RS-485 line
    rs485_delays: tuple[float, float] | None = None  # seconds RTS leads and trails a frame
    pause: float = 0.0  # seconds at least between a reply and the next request (slow devices)
    connect_delay: float = 0.0  # seconds to wait after opening the link, before the first request
    reconnect_each: bool = False  # polling: a new link for every poll
    lenient: bool = False  # accept replies that break the spec harmlessly, with a warning


def framer_name(connection: Connection) -> str:
    from mbtool.link.transport import default_framer

    return connection.framer or default_framer(connection.port or "")


def check(connection: Connection, needs: str = "", opening: bool = True) -> str:
    """The framing's name, once the connection makes sense; RequestError (nothing sent) if not.

    ``needs``: what the command does, named when it may not go to unit 0 (broadcast is
    for writes only, spec §2; an empty ``needs`` allows it).  ``opening``: the link is to
    be opened, so a port is needed (a dry run opens none).
    """
    from mbtool.codec.framing import is_broadcast

    if not connection.port and opening:
        raise RequestError(
            "no port given: use -p TARGET or set MBTOOL_PORT (try -p sim:// for the built-in device)"
        )
    name = framer_name(connection)
    if connection.echo and (connection.port or "").lower().startswith("tcp://"):
        raise RequestError("--echo strips a half-duplex serial adapter's echo; a tcp:// link has none")
    if needs and is_broadcast(connection.unit, name):
        raise RequestError(
            f"unit 0 is broadcast in {name.upper()} framing, which only writes may use; {needs} needs a unit 1..255"
        )
    return name


@contextmanager
def open_client(
    connection: Connection,
    needs: str = "",
    framer: Framer | None = None,
    trace: Callable[[Framer], Trace] | None = None,
) -> Iterator[Client]:
    """A Client on the connection's link, closed afterwards.

    ``framer`` replaces the default one; ``trace`` makes the Client's trace from the framer
    (--hex).  Several transactions can share the link (diag counters, device-id's
    more-follows; sim:// keeps its state only as long as its link).
    """
    from mbtool.codec.framing import make_framer
    from mbtool.link.client import Client
    from mbtool.link.transport import SerialSettings, open_transport

    name = check(connection, needs)
    settings = SerialSettings(
        connection.baud,
        connection.parity,
        connection.bytesize,
        connection.stopbits,
        rs485_direction(connection),
    )
    transport = open_transport(connection.port, settings, connection.timeout, name)
    try:
        framer = framer or make_framer(name)
        client = Client(
            transport,
            framer,
            timeout=connection.timeout,
            retries=connection.retries,
            echo=connection.echo,
            baud=connection.baud,
            char_bits=settings.char_bits,
            pause=connection.pause,
            lenient=connection.lenient,
        )
        if trace is not None:
            client.trace = trace(framer)
        if connection.connect_delay:
            # Some devices drop a request sent right after the TCP handshake.
            time.sleep(connection.connect_delay)
        yield client
    finally:
        transport.close()


def close_quietly(link: ExitStack) -> None:
    """Close a link that may already have broken (polling, scan): nothing left to report."""
    from mbtool.errors import KNOWN_ERRORS

    try:
        link.close()
    except (*KNOWN_ERRORS, OSError):
        pass


def rs485_direction(connection: Connection) -> tuple[float, float] | None:
    """RTS lead and trail in seconds when RTS switches the line's direction, else None."""
    delays = rs485_delays(connection.rs485, connection.rs485_delays)
    if delays and (connection.port or "").lower().startswith("tcp://"):
        raise RequestError("--rs485 drives the RTS line of a serial port; a tcp:// target has none")
    return delays


def rs485_delays(rs485: bool, delays: tuple[float, float] | None) -> tuple[float, float] | None:
    """What --rs485 and --rs485-delays ask: RTS lead and trail, or None for no RTS switching.
    Delays alone turn the mode on: nobody sets them without meaning it."""
    if not (rs485 or delays):
        return None
    return delays or (0.0, 0.0)
