"""Several transactions over one link (diag counters, device-id's more-follows, raw --adu).

``connection.execute`` opens, runs one request and closes; these commands need
the link to stay open between requests (the sim:// device keeps its state only
as long as its link, and a serial port should not be reopened per counter).
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

from mbtool.connection import Connection
from mbtool.errors import RequestError


@contextmanager
def open_client(connection: Connection, broadcastable: bool = False, framer=None) -> Iterator[object]:
    """A Client on the connection's link, closed afterwards; ``framer`` replaces the default one."""
    from mbtool.client import Client
    from mbtool.codec.framing import make_framer
    from mbtool.render import HexTrace
    from mbtool.transport import SerialSettings, default_framer, open_transport

    if not connection.port:
        raise RequestError(
            "no port given: use -p TARGET or set MBTOOL_PORT (try -p sim:// for the built-in device)"
        )
    if connection.unit == 0 and not broadcastable:
        raise RequestError("unit 0 is broadcast, which only writes may use; this command needs a unit 1..255")
    framer_name = connection.framer or default_framer(connection.port)
    settings = SerialSettings(connection.baud, connection.parity, connection.bytesize, connection.stopbits)
    transport = open_transport(connection.port, settings, connection.timeout, framer_name)
    try:
        framer = framer or make_framer(framer_name)
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


def framer_name(connection: Connection) -> str:
    from mbtool.transport import default_framer

    return connection.framer or default_framer(connection.port or "")
