"""A connection as the options describe it, and running one request over it."""

from __future__ import annotations

import sys

from mbtool.codec.record import record, replace
from mbtool.errors import RequestError


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


def execute(connection: Connection, request) -> object:
    """Open the link, run one transaction, close it; the reply (None for broadcast)."""
    from mbtool.client import Client
    from mbtool.codec.framing import make_framer
    from mbtool.render import HexTrace
    from mbtool.transport import SerialSettings, default_framer, open_transport

    if not connection.port:
        raise RequestError(
            "no port given: use -p TARGET or set MBTOOL_PORT (try -p sim:// for the built-in device)"
        )
    if connection.unit == 0 and not request.broadcastable:
        raise RequestError(
            f"unit 0 is broadcast, which only writes may use; {request.name} needs a unit 1..255"
        )
    framer_name = connection.framer or default_framer(connection.port)
    settings = SerialSettings(connection.baud, connection.parity, connection.bytesize, connection.stopbits)
    transport = open_transport(connection.port, settings, connection.timeout, framer_name)
    try:
        framer = make_framer(framer_name)
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
        return client.execute(connection.unit, request)
    finally:
        transport.close()


def show(connection: Connection, result) -> None:
    from mbtool.render import default_format, render

    if connection.unit == 0:
        result = replace(result, note="broadcast: no device confirms a write to unit 0")
        print(f"mbtool: {result.note}", file=sys.stderr)
    render(result, connection.output_format or default_format())
