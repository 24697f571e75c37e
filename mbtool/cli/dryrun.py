"""--dry-run: the frames a command would send, decoded field by field, and nothing sent.

A user about to write to a live plant checks the frame first (issue 6).  The
port is never opened, so a dry run needs no hardware.  A command that cannot go
on without a reply (every one: it needs the reply to print) stops after its
first request with ``DryRunDone``, which leaves through exit 0.
"""

from __future__ import annotations

from mbtool.cli.frames import frame_report
from mbtool.cli.sinks import RESULTS, default_format, formats, render
from mbtool.codec.describe import describe
from mbtool.errors import ExitCode, MbtoolError


class DryRunDone(MbtoolError):
    """The dry run has shown what it can know before any reply: success, one stderr line."""

    exit_code = ExitCode.OK


class DryRunClient:
    """Stands in for a Client: builds and shows each frame instead of sending it."""

    def __init__(self, framer, settings, then: str = "") -> None:
        self.framer = framer
        self.settings = settings  # the run's: its -o and --no-header
        self.then = then  # what a multi-request command would do next, for the closing line
        self.shown = 0
        self.trace = None  # raw wraps the trace; nothing is ever traced here

    def show(self, unit: int, request) -> None:
        """Print the frame that would go out for this request."""
        # Transaction id 1: the first one a real Client would use.
        adu = self.framer.build(unit, request.encode(), 1)
        name = self.framer.name
        text = adu.decode("ascii", "replace") if name == "ascii" else adu.hex(" ")
        described = describe(text, name, "request")
        fmt = self.settings.output_format
        fmt = fmt if fmt in formats(RESULTS) else default_format()  # not influx, prom
        render(frame_report(described, header=self.shown == 0), fmt, csv_header=self.settings.csv_header)
        self.shown += 1

    def execute(self, unit: int, request):
        self.show(unit, request)
        self.finish(unit)

    def finish(self, unit: int) -> None:
        note = "dry run: nothing sent (the port was not opened)"
        if unit == self.framer.broadcast_unit:
            note += "; broadcast: no device would confirm this write to unit 0"
        if self.then:
            note += f"; {self.then}"
        raise DryRunDone(note)
