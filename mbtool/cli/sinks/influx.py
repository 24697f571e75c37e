"""-o influx: InfluxDB line protocol, to the reference's letter: the escaping (measurement:
commas and spaces; tag keys, tag values and field keys: commas, equals signs and spaces;
backslashes doubled in all of them; string field values: double quotes and backslashes),
a field's type fixed by its point (``Point.number_of``), integers with ``i`` and
nanosecond timestamps.  A line a read (``Readings``, read -o influx) or a device poll
(``poll_line``, poll -o influx).
"""

from __future__ import annotations

import math
import sys
import time

from mbtool.cli.metrics import ReadingPolls, values_of
from mbtool.cli.metrics import Readings as MonitoringReadings
from mbtool.cli.results import Points

Polls = ReadingPolls  # read --interval: each poll through the run's Readings


class Readings(MonitoringReadings):
    """A read command's -o influx: a line a read; the fields warned about so far."""

    influx = True

    def emit(self, result, out, when: float | None = None) -> None:
        out.write(self.result_line(result, when))

    def emit_failure(self, error: BaseException, out) -> None:
        """The line protocol has no news of a device down: a line is written only for values read."""

    def result_line(self, result, when: float | None = None) -> str:
        """One line a poll: tags for the unit (and table, device), a field a value.

        A value the protocol cannot carry (NaN, an infinity) is left out with a warning,
        once a run for each field; a read left with no field writes no line, as a point
        must have one."""
        tags = {"unit": str(result.unit)}
        points = isinstance(result, Points)
        if not points:
            tags["table"] = result.table
        if self.device:
            tags["device"] = self.device
        fields = []
        for labels, value, _ in values_of(result):
            if points:
                key = labels["name"]
            else:
                key = labels.get("ref", labels["address"]) + (
                    f"_{labels['order']}" if "order" in labels else ""
                )
            shown = field_value(value)
            if shown is None:
                self._warn_left_out(f"{key} ({labels['ref']})" if points else f"{result.table} {key}", value)
                continue
            fields.append(f"{escape(key, KEY_SPECIALS)}={shown}")
        stamp = time.time_ns() if when is None else int(when * 1_000_000_000)
        return line(self.measurement, tags, fields, stamp)

    def _warn_left_out(self, what: str, value: object) -> None:
        if what not in self.warned:
            self.warned.add(what)
            print(
                f"mbtool: warning: {what} reads {value}: left out of the InfluxDB line "
                "(it has no NaN or infinity)",
                file=sys.stderr,
                flush=True,
            )


def escape(text: str, specials: str) -> str:
    """The reference's escaping: a backslash before each special character, and a backslash
    itself doubled (two contiguous backslashes are one), so one at the end of a name never
    escapes the separator after it."""
    text = text.replace("\\", "\\\\")
    for char in specials:
        text = text.replace(char, "\\" + char)
    return text


MEASUREMENT_SPECIALS = ", "  # commas and spaces
KEY_SPECIALS = ",= "  # tag keys, tag values and field keys: commas, equals signs and spaces


def field_value(value) -> str | None:
    """The value as the line protocol writes it; None for NaN and the infinities, which it
    cannot carry."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return f"{value}i"
    if isinstance(value, float):
        return repr(value) if math.isfinite(value) else None
    return '"' + str(value).replace("\\", "\\\\").replace('"', '\\"') + '"'


def line(measurement: str, tags: dict[str, str], fields: list[str], stamp_ns: int) -> str:
    """One line of the line protocol: the measurement and its tags escaped (sorted, an empty
    one left out), the fields as given (``key=value``, escaped), the time in nanoseconds;
    "" when there is no field, as a line must have one."""
    if not fields:
        return ""
    head = escape(measurement, MEASUREMENT_SPECIALS) + "".join(
        f",{escape(k, KEY_SPECIALS)}={escape(v, KEY_SPECIALS)}" for k, v in sorted(tags.items()) if v
    )
    return f"{head} {','.join(fields)} {stamp_ns}\n"


def poll_line(poll, measurement: str) -> str:
    """One line a device poll (plant.schedule.Poll): its measurement, tags device, unit and the
    device's tags, a field a point read (its type fixed by its map entry; NaN and infinities
    left out)."""
    device = poll.device
    fields = []
    for reading in poll.readings or ():
        if reading.error is not None or reading.value is None:
            continue
        number = reading.point.number_of(reading.value)
        shown = field_value(reading.value if number is None else number)
        if shown is not None:
            fields.append(f"{escape(reading.point.name, KEY_SPECIALS)}={shown}")
    tags = {"device": device.name, "unit": str(device.unit)} | (device.tags or {})
    return line(measurement, tags, fields, int(poll.time * 1_000_000_000))


class PlantPolls:
    """poll -o influx: a line a device poll, in the device's measurement (else the run's)."""

    measured = True  # --measurement names its measurement
    exposes = False

    def __init__(self, out, csv_header: bool, measurement: str, labels: dict | None = None) -> None:
        self.out = out
        self.measurement = measurement

    def poll(self, poll, when: str) -> None:
        self.out.write(poll_line(poll, poll.device.measurement or self.measurement))

    def event(self, event, when: str) -> None:
        """The line protocol has no news of a device down."""
