"""A connection as the options describe it, checked, and a Client opened over it."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from contextlib import ExitStack, contextmanager
from typing import TYPE_CHECKING

from mbtool.codec.framer import Framer
from mbtool.codec.framing import is_broadcast, make_framer
from mbtool.codec.record import record
from mbtool.errors import KNOWN_ERRORS, UsageError
from mbtool.link.settings import SECURITY, SETTINGS, check_tls_framing, default, misplaced

# link.transport and link.client are imported where a link is opened or checked: every command
# loads Connection (cli.options), crc too, and they cost it 5-7 M instructions.
if TYPE_CHECKING:
    from mbtool.link.client import Client, Trace


@record
class Connection:
    """Built from keywords: what -p, -u and the line options say about the link.  Each field is
    a setting of ``link.settings.SETTINGS``, which gives its default, its help and its checks;
    the fields are written out so that a reader (and a type checker) sees them."""

    port: str | None = default("port")
    unit: int = default("unit")
    framer: str | None = default("framer")  # None: tcp for tcp://, rtu for everything else
    baud: int = default("baud")
    parity: str = default("parity")
    bytesize: int = default("bytesize")
    stopbits: int = default("stopbits")
    timeout: float = default("timeout")
    retries: int = default("retries")
    echo: bool = default("echo")  # a half-duplex adapter echoes every byte sent
    rs485: bool = default("rs485")  # drive RTS for the direction of a two-wire RS-485 line
    rs485_delays: tuple[float, float] | None = default("rs485_delays")  # seconds RTS leads and trails a frame
    pause: float = default("pause")  # seconds at least between a reply and the next request (slow devices)
    connect_delay: float = default("connect_delay")  # seconds to wait after opening the link
    reconnect_each: bool = default("reconnect_each")  # polling: a new link for every poll
    lenient: bool = default("lenient")  # accept replies that break the spec harmlessly, with a warning
    # tls:// (Modbus/TCP Security): the client's certificate and key (PEM), the CAs (or the
    # device's own certificate) to trust, no check of the server's certificate, and the name
    # it must have where it is not the host's.
    cert: str | None = default("cert")
    key: str | None = default("key")
    ca: str | None = default("ca")
    insecure: bool = default("insecure")
    server_name: str | None = default("server_name")


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
    if connection.echo and is_network(port):
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
            if getattr(connection, name) and port:
                raise misplaced(SETTINGS[name], port)
        return
    check_tls_framing(framing)
    if connection.insecure and connection.ca:  # (--server-name still names the server it asks for: SNI)
        raise UsageError("--insecure checks no certificate: --ca would have nothing to check")


def tls_settings(connection: Connection):
    """The TlsSettings of a tls:// connection (mbtool.link.tls)."""
    from mbtool.link.tls import TlsSettings  # noqa: PLC0415 - ssl, 6 ms: tls:// only

    return TlsSettings(
        connection.cert, connection.key, connection.ca, connection.insecure, connection.server_name
    )


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
    settings = SerialSettings(
        connection.baud,
        connection.parity,
        connection.bytesize,
        connection.stopbits,
        rs485_direction(connection),
    )
    port = connection.port
    assert port is not None  # check() refused a link to open without one
    secure = tls_settings(connection) if port.lower().startswith("tls://") else None
    transport = open_transport(port, settings, connection.timeout, name, secure)
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
    try:
        link.close()
    except (*KNOWN_ERRORS, OSError):
        pass


def rs485_direction(connection: Connection) -> tuple[float, float] | None:
    """RTS lead and trail in seconds when RTS switches the line's direction, else None."""
    from mbtool.link.transport import is_network  # noqa: PLC0415 - 5-7 M instructions: crc too

    delays = rs485_delays(connection.rs485, connection.rs485_delays)
    if delays and is_network(connection.port or ""):
        raise misplaced(SETTINGS["rs485"], connection.port or "")
    return delays


def rs485_delays(rs485: bool, delays: tuple[float, float] | None) -> tuple[float, float] | None:
    """What --rs485 and --rs485-delays ask: RTS lead and trail, or None for no RTS switching.
    Delays alone turn the mode on: nobody sets them without meaning it."""
    if not (rs485 or delays):
        return None
    return delays or (0.0, 0.0)
