"""A connection as the options describe it, and running one request over it."""

from __future__ import annotations

import sys
from collections.abc import Iterator
from contextlib import contextmanager
from typing import TYPE_CHECKING

from mbtool.codec.errors import RequestError
from mbtool.codec.record import record, replace

if TYPE_CHECKING:
    from mbtool.link.client import Client


@record
class Connection:
    port: str | None
    unit: int
    framer: str | None
    baud: int
    parity: str
    bytesize: int
    stopbits: int
    timeout: float
    retries: int
    echo: bool
    hex: bool
    output_format: str | None
    dry_run: bool = False  # show the frames, open nothing, send nothing
    rs485: bool = False  # drive RTS for the direction of a two-wire RS-485 line
    rs485_delays: tuple[float, float] | None = None  # seconds RTS leads and trails a frame


@contextmanager
def open_client(connection: Connection, needs: str = "", framer=None, then: str = "") -> Iterator[Client]:
    """A Client on the connection's link, closed afterwards.

    ``needs``: what the command does, named when it may not go to unit 0 (broadcast
    is for writes only; an empty ``needs`` allows it).  ``framer`` replaces the default.
    ``then``: with --dry-run, what the command would send after the first reply.
    Several transactions can share the link (diag counters, device-id's more-follows;
    sim:// keeps its state only as long as its link).
    """
    from mbtool.cli.render import HexTrace
    from mbtool.codec.framing import is_broadcast, make_framer
    from mbtool.link.client import Client
    from mbtool.link.transport import SerialSettings, open_transport

    if not connection.port and not connection.dry_run:
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
    if connection.dry_run:
        from mbtool.cli.dryrun import DryRunClient

        yield DryRunClient(framer or make_framer(name), connection.output_format, then)
        return
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
        )
        if connection.hex:
            client.trace = HexTrace(framer)
        yield client
    finally:
        transport.close()


def close_quietly(link) -> None:
    """Leave an open_client context whose link may already have broken (polling, scan)."""
    from mbtool.errors import KNOWN_ERRORS

    if link is not None:
        try:
            link.__exit__(None, None, None)
        except (*KNOWN_ERRORS, OSError):
            pass  # closing a link that already broke: nothing left to report


def rs485_direction(connection: Connection) -> tuple[float, float] | None:
    """RTS lead and trail in seconds when RTS switches the line's direction, else None.

    Delays alone turn the mode on: nobody sets them without meaning it.
    """
    if not (connection.rs485 or connection.rs485_delays):
        return None
    if (connection.port or "").lower().startswith("tcp://"):
        raise RequestError("--rs485 drives the RTS line of a serial port; a tcp:// target has none")
    return connection.rs485_delays or (0.0, 0.0)


def framer_name(connection: Connection) -> str:
    from mbtool.link.transport import default_framer

    return connection.framer or default_framer(connection.port or "")


def execute(connection: Connection, request) -> object:
    """Open the link, run one transaction, close it; the reply (None for broadcast)."""
    with open_client(connection, "" if request.broadcastable else request.name) as client:
        return client.execute(connection.unit, request)


def show(connection: Connection, result) -> None:
    from mbtool.cli.render import default_format, render
    from mbtool.codec.framing import is_broadcast

    if is_broadcast(connection.unit, framer_name(connection)):
        result = replace(result, note="broadcast: no device confirms a write to unit 0")
        print(f"mbtool: {result.note}", file=sys.stderr)
    render(result, connection.output_format or default_format())
