"""The output formats: one module a format in this package, and this registry of them
(httpie's formatters, sqlite-utils' --fmt): each -o a command offers is a list made here.

A sink is the module that writes one format, ``mbtool.cli.sinks.NAME``: ``render`` for a
one-shot result (cli/results.py), and what the commands that offer it need of it (a poll's
line, a plant's record, an exposition), each a public function or class.  It is imported
when the format is chosen, not before: rich (the table), the line protocol and the
Prometheus text cost a one-shot nothing it does not write.

A new format is its module and one line in ``SINKS``, with the kinds of output it
writes; every -o that offers that kind offers it.
"""

from __future__ import annotations

import sys
from importlib import import_module
from types import ModuleType
from typing import TextIO

from mbtool.codec.record import record

# The kinds of output a command writes, each offered in the formats that can write it.
RESULTS = "results"  # a one-shot result, a report or a map's points (read, write, decode...), and its polls
READINGS = "readings"  # values read alone, for a monitoring system (the read commands)
PLANT = "plant"  # poll's stream of device polls
LOG = "log"  # a stream of frames or transactions (monitor, bridge)


@record
class Sink:
    name: str  # -o NAME, and the module mbtool.cli.sinks.NAME
    about: str  # what it writes, in a few words
    kinds: set[str]  # RESULTS, READINGS, PLANT, LOG: the outputs it writes
    errors: bool = False  # a failure is one of its records too ({"error", "exit_code"}: program.main)
    blocks: bool = False  # its results are blocks of text for people: a blank line between two


REGISTRY = (
    Sink("table", "a table on a terminal (rich)", {RESULTS, LOG}, blocks=True),
    Sink("plain", "plain lines, a value a line", {RESULTS, PLANT, LOG}, blocks=True),
    Sink("json", "a JSON object (a line each, when polling)", {RESULTS, PLANT, LOG}, errors=True),
    Sink("csv", "CSV: a header row, then a row a value", {RESULTS, PLANT}),
    Sink("influx", "InfluxDB line protocol", {READINGS, PLANT}),
    Sink("prom", "Prometheus text exposition", {READINGS, PLANT}),
)
SINKS = {sink.name: sink for sink in REGISTRY}


def formats(*kinds: str) -> tuple[str, ...]:
    """The names of the formats that write any of ``kinds``, in the registry's order: an -o's choices."""
    return tuple(name for name, sink in SINKS.items() if sink.kinds & set(kinds))


def sink(name: str) -> ModuleType:
    """The module that writes format ``name``."""
    return import_module(f"{__name__}.{name}")


# The stream is looked up when called, not bound as a default: cli.main may put a stdout in
# place of a closed one after this module is imported.
def default_format(stream: TextIO | None = None) -> str:
    """The terminal's format when -o is not given (httpie's rule): a table on a TTY, plain
    lines in a pipe."""
    return "table" if (stream or sys.stdout).isatty() else "plain"


def render(result, fmt: str, out: TextIO | None = None, *, csv_header: bool = True) -> None:
    """A one-shot result (cli.results: Result, Report or Points) in format ``fmt``.
    ``csv_header``: the run's settings (False with --no-header)."""
    sink(fmt).render(result, out or sys.stdout, csv_header)
