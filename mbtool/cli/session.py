"""Running a command's requests the way the options ask: over the link, traced (--hex),
or only shown (--dry-run); and the result printed in the chosen format.

What every device command shares lives here, so that commands never import one
another and the link knows nothing of rendering: each function takes the link's
``Connection`` and the run's ``Settings``.
"""

from __future__ import annotations

import sys
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

from mbtool.cli.settings import Settings
from mbtool.cli.sinks import default_format, render
from mbtool.codec.framing import is_broadcast, make_framer
from mbtool.codec.record import replace
from mbtool.link.connection import Connection, check, framer_name, is_tls
from mbtool.link.connection import open_client as open_link


@contextmanager
def open_client(
    connection: Connection, settings: Settings, needs: str = "", framer=None, then: str = ""
) -> Iterator:
    """A Client on the connection's link (see link.connection.open_client), traced with
    --hex; with --dry-run a stand-in that shows each request's frame and opens nothing.

    ``then``: with --dry-run, what the command would send after the first reply.
    """
    if settings.dry_run:
        from mbtool.cli.dryrun import DryRunClient  # noqa: PLC0415 - describe, 0.8 ms: --dry-run only

        name = check(connection, needs, opening=False)
        yield DryRunClient(framer or make_framer(name), settings, then)
        return
    with open_link(connection, needs, framer, trace_for(settings)) as client:
        yield client
        for deviation in client.deviations:
            print(f"mbtool: warning: {deviation} (accepted: --lenient)", file=sys.stderr)


def warn_insecure(connection: Connection, link: str = "") -> None:
    """--insecure, on every run that uses it: the server's certificate goes unchecked.
    ``link``: the inventory's name of the link (poll).  The connection is checked first: a
    mistake in the options (--insecure with --ca) is said alone, not after the warning."""
    port = connection.port or ""
    if connection.tls.insecure and is_tls(connection):
        check(connection)
        named = f" (link {link})" if link else ""
        print(
            f"mbtool: warning: --insecure: the certificate of {port}{named} is not checked, so anyone "
            "on the way can read and change the traffic",
            file=sys.stderr,
        )


def trace_for(settings: Settings):
    """What makes a Client's trace from its framer: --hex's, or None for no trace."""
    if not settings.hex:
        return None
    from mbtool.cli.frames import HexTrace  # noqa: PLC0415 - --hex only

    return HexTrace


def execute(connection: Connection, settings: Settings, request) -> Any:
    """Open the link, run one transaction, close it; the reply (None for broadcast).

    Any: the reply's class is the one its request decodes (``request.decode_response``),
    which the command that built the request knows and the checker cannot follow."""
    with open_client(connection, settings, "" if request.broadcastable else request.name) as client:
        return client.execute(connection.unit, request)


def show(connection: Connection, settings: Settings, result, metrics=None) -> None:
    """Print a command's result; a write to unit 0 says on stderr that nobody confirmed it.
    ``metrics``: the run's cli.metrics.Metrics, which writes -o influx and prom (only the
    read commands offer them: device_command)."""
    if is_broadcast(connection.unit, framer_name(connection)):
        result = replace(result, note="broadcast: no device confirms a write to unit 0")
        print(f"mbtool: {result.note}", file=sys.stderr)
    if metrics is not None:
        metrics.emit(result, sys.stdout)
        return
    render(result, settings.output_format or default_format(), csv_header=settings.csv_header)
