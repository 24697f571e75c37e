"""What a read command's -o influx and -o prom share (``Readings``, each sink's subclass:
cli/sinks/influx.py, cli/sinks/prom.py): the names they refuse, the values they write, each
with what names it, and what a run learns as it goes.  Only the read commands offer them
(``readings`` in ``device_command``).

A run writes them through one ``Readings``, made from its settings: what it learns as it
goes (when the device last answered, the fields it warned about) is the run's own.
"""

from __future__ import annotations

from abc import ABC, abstractmethod

from mbtool.cli.results import Points
from mbtool.cli.settings import Settings
from mbtool.errors import ExitCode, UsageError, exit_code_for

# The failures that mean the device could not be read: no reply, an exception (to every
# point of a map), a reply that is not one, a link that cannot be opened.
DEVICE_FAILURES = (ExitCode.TIMEOUT, ExitCode.EXCEPTION, ExitCode.INVALID_RESPONSE, ExitCode.CONNECTION)


class Readings(ABC):
    """One run's -o influx or -o prom (--textfile): its measurement, its profile's name, its
    textfile, the unit the status metrics name when no result does; and what the run has
    learnt: when the device last answered, the fields left out of a line so far."""

    influx = False  # the line protocol's rules for names (name_problem)

    def __init__(self, settings: Settings, unit: int) -> None:
        self.measurement = settings.measurement
        self.device = settings.device
        self.textfile = settings.textfile
        self.unit = unit
        self.last_success: float | None = None  # when the device last answered a read (Unix time)
        self.warned: set[str] = set()  # the fields left out so far, each warned about once
        self.swept = False  # the textfile's stale temporaries have been looked for

    def check(self, points=()) -> None:
        """Refuse, before anything is sent, a measurement or profile name the output cannot
        carry (name_problem).  A map's point names are held to one line when the map is loaded."""
        names = [("--measurement", self.measurement, "a measurement")]
        if self.device:
            names.append(("profile", self.device, "a tag or label"))
        for option, name, what in names:
            problem = name_problem(name, what, influx=self.influx)
            if problem:
                raise UsageError(f"{option} {name!r}: {problem}")

    @abstractmethod
    def emit(self, result, out, when: float | None = None) -> None:
        """One read, written to ``out`` (or the textfile): each format's own."""

    @abstractmethod
    def emit_failure(self, error: BaseException, out) -> None:
        """A read that failed, as each format says it."""

    @staticmethod
    def device_failed(error: BaseException) -> bool:
        """The device could not be read (not a bad request, nor a full disk)."""
        return exit_code_for(error) in DEVICE_FAILURES


def name_problem(name: str, what: str, influx: bool) -> str:
    """Why ``name`` cannot be written; "" when it can (registermap.load.name_problem: the
    inventory's loader checks a device's measurement by it too)."""
    from mbtool.registermap.load import name_problem  # noqa: PLC0415 - the map loader, 4-8 ms: -m only

    return name_problem(name, what, influx)


def values_of(result) -> list[tuple[dict, object, str]]:
    """Each value with what names it: (labels, value, help) for both formats."""
    if isinstance(result, Points):
        out = []
        for row in result.rows:
            if row.value is None:
                continue  # no data (the map's invalid key): no field, no sample
            number = row.value if row.number is None else row.number  # text stays text
            about = (row.description or row.name) + (f" ({row.unit})" if row.unit else "") + f", {row.ref}"
            out.append(({"name": row.name, "ref": row.ref}, number, about))
        return out
    table = result.table
    refs = result.refs or [None] * len(result.values)
    out = []
    for ref, address, value in zip(refs, result.addresses, result.values, strict=True):
        labels = {"table": table, "address": str(address)} | ({"ref": ref} if ref else {})
        if isinstance(value, dict):  # --order all: one value an order
            out += [(labels | {"order": order}, each, "") for order, each in value.items()]
        else:
            out.append((labels, value, ""))
    return out


class ReadingPolls:
    """read --interval -o influx or -o prom: each poll through the run's Readings, to stdout
    with the other writes (one flush a gap) or to the textfile at once; a failed poll, for
    Prometheus, as the device down.  (A poll's Output, cli.poll_output, as the sinks' Polls.)"""

    changes_as_rows = False

    def __init__(self, output) -> None:
        self.output = output

    def change(self, when: str, what: dict, where: str, old, new, unit: str) -> None:
        """Never called: --changes goes with neither format (read refuses it before anything is sent)."""

    def close(self) -> None:
        pass

    def result(self, when: str, result, stamp: float | None = None) -> None:
        metrics = self.output.metrics
        metrics.emit(result, None if metrics.textfile else self.output.pending, stamp)

    def values(self, when: str, read, values: list, registers, stamp: float | None = None) -> None:
        self.result(when, read.polled(values, registers), stamp)

    def failure(self, when: str, error: BaseException) -> None:
        metrics = self.output.metrics
        metrics.emit_failure(error, None if metrics.textfile else self.output.pending)
