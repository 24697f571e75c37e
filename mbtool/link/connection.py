"""A connection as the options describe it, checked, and a Client opened over it."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from contextlib import ExitStack, contextmanager
from typing import TYPE_CHECKING

from mbtool.codec.framer import Framer
from mbtool.codec.framing import is_broadcast, make_framer
from mbtool.codec.record import record, replace
from mbtool.errors import KNOWN_ERRORS, UsageError
from mbtool.link.settings import (
    RECORDS,
    SECURITY,
    SETTINGS,
    SerialLine,
    TlsSettings,
    check_tls_framing,
    default,
    misplaced,
)

# link.transport and link.client are imported where a link is opened or checked: every command
# loads Connection (cli.options), crc too, and they cost it 5-7 M instructions.
if TYPE_CHECKING:
    from mbtool.link.client import Client, Trace


@record
class Connection:
    """What -p, -u and the line options say about the link.  Each field is a setting of
    ``link.settings.SETTINGS`` for every link, which gives its default, its help and its
    checks; a transport's own settings are its record (``serial``: a serial line's, ``tls``:
    a tls:// link's), which its code reads alone.  Made from the settings by their names with
    ``connection_of``; the fields are written out so that a reader (and a type checker) sees them."""

    port: str | None = default("port")
    unit: int = default("unit")
    framer: str | None = default("framer")  # None: tcp for tcp://, rtu for everything else
    timeout: float = default("timeout")
    retries: int = default("retries")
    pause: float = default("pause")  # seconds at least between a reply and the next request (slow devices)
    connect_delay: float = default("connect_delay")  # seconds to wait after opening the link
    reconnect_each: bool = default("reconnect_each")  # polling: a new link for every poll
    lenient: bool = default("lenient")  # accept replies that break the spec harmlessly, with a warning
    serial: SerialLine = SerialLine()
    tls: TlsSettings = TlsSettings()


def connection_of(**settings) -> Connection:
    """A Connection from settings by their names in ``SETTINGS`` (the options', a profile's
    keys, an inventory link's): each to its transport's record, by its row."""
    return changed(Connection(), **settings)


def changed(connection: Connection, **settings) -> Connection:
    """``connection`` with ``settings`` (by their names in ``SETTINGS``) changed, each in its
    transport's record."""
    records: dict[str, dict] = {}
    common = {}
    for name, value in settings.items():
        transport = SETTINGS[name].transport
        if transport:
            records.setdefault(RECORDS[transport][0], {})[name] = value
        else:
            common[name] = value
    for field, values in records.items():
        common[field] = replace(getattr(connection, field), **values)
    return replace(connection, **common) if common else connection


def framer_name(connection: Connection) -> str:
    from mbtool.link.transport import default_framer  # noqa: PLC0415 - 5-7 M instructions: crc too

    return connection.framer or default_framer(connection.port or "")


def check(connection: Connection, needs: str = "", opening: bool = True) -> str:
    """The framing's name, once the connection makes sense; UsageError (nothing sent) if not.

    ``needs``: what the command does, named when it may not go to unit 0 (broadcast is
    for writes only, spec §2; an empty ``needs`` allows it).  ``opening``: the link is to
    be opened, so a port is needed (a dry run opens none).
    """
    if not connection.port and opening:
        raise UsageError(
            "no port given: use -p TARGET or set MBTOOL_PORT (try -p sim:// for the built-in device)"
        )
    from mbtool.link.transport import is_network  # noqa: PLC0415 - 5-7 M instructions: crc too

    name = framer_name(connection)
    port = connection.port or ""
    if connection.serial.echo and is_network(port):
        raise misplaced(SETTINGS["echo"], port)
    _check_tls(connection, port, name)
    if needs and is_broadcast(connection.unit, name):
        raise UsageError(
            f"unit 0 is broadcast in {name.upper()} framing, which only writes may use; {needs} needs a unit 1..255"
        )
    return name


def _check_tls(connection: Connection, port: str, framing: str) -> None:
    """The TLS settings go with a tls:// target, which carries MBAP (Modbus/TCP Security)."""
    if port.partition("://")[0].lower() != "tls":
        for name in SECURITY:
            if getattr(connection.tls, name) and port:
                raise misplaced(SETTINGS[name], port)
        return
    check_tls_framing(framing)
    if (
        connection.tls.insecure and connection.tls.ca
    ):  # (--server-name still names the server it asks for: SNI)
        raise UsageError("--insecure checks no certificate: --ca would have nothing to check")


def is_tls(connection: Connection) -> bool:
    """Whether the link is tls:// (Modbus/TCP Security), whose ``tls`` settings it uses."""
    return (connection.port or "").lower().startswith("tls://")


def read_credentials(connection: Connection) -> None:
    """A tls:// link's files read now, before anything opens: a bad one is exit 2, and an
    encrypted key's password is asked once, here, not on each reconnect (its context is kept)."""
    if is_tls(connection):
        from mbtool.link.tls import client_context  # noqa: PLC0415 - ssl, 6 ms: tls:// only

        client_context(connection.tls)


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
    from mbtool.link.client import Client  # noqa: PLC0415 - 5-7 M instructions: crc too
    from mbtool.link.transport import (  # noqa: PLC0415 - 5-7 M instructions: crc too
        SerialSettings,
        open_transport,
    )

    name = check(connection, needs)
    line = connection.serial
    settings = SerialSettings(
        line.baud, line.parity, line.bytesize, line.stopbits, rs485_direction(connection)
    )
    port = connection.port
    assert port is not None  # check() refused a link to open without one
    transport = open_transport(
        port, settings, connection.timeout, name, connection.tls if is_tls(connection) else None
    )
    try:
        framer = framer or make_framer(name)
        client = Client(
            transport,
            framer,
            timeout=connection.timeout,
            retries=connection.retries,
            echo=line.echo,
            baud=line.baud,
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
    try:
        link.close()
    except (*KNOWN_ERRORS, OSError):
        pass


def rs485_direction(connection: Connection) -> tuple[float, float] | None:
    """RTS lead and trail in seconds when RTS switches the line's direction, else None."""
    from mbtool.link.transport import is_network  # noqa: PLC0415 - 5-7 M instructions: crc too

    delays = rs485_delays(connection.serial.rs485, connection.serial.rs485_delays)
    if delays and is_network(connection.port or ""):
        raise misplaced(SETTINGS["rs485"], connection.port or "")
    return delays


def rs485_delays(rs485: bool, delays: tuple[float, float] | None) -> tuple[float, float] | None:
    """What --rs485 and --rs485-delays ask: RTS lead and trail, or None for no RTS switching.
    Delays alone turn the mode on: nobody sets them without meaning it."""
    if not (rs485 or delays):
        return None
    return delays or (0.0, 0.0)
