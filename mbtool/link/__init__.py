"""Master side I/O: transports, the client (time, retries, id matching), connections, the managed link, polling.

The registry of in-process links lives here, not in ``transport``: the CLI registers
``sim://`` on every start, and this costs it no socket or serial imports.
"""

from __future__ import annotations

from collections.abc import Callable

# Links that answer in-process, by scheme: ``opener(framer_name)`` opens a Transport.  The
# master side knows no device; the CLI registers ``sim://`` (mbtool.device's simulated one).
IN_PROCESS: dict[str, Callable] = {}


def register_scheme(scheme: str, opener: Callable) -> None:
    IN_PROCESS[scheme] = opener
