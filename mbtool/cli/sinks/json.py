"""-o json, and JSON text: the one writer of it in the CLI, for every object a command prints.

One rule for all: json's separators, and NaN and the infinities as null (they are no
JSON; jq would choke on them).  One object (a one-shot read, an error) is written by
``to_json``, without the json module: importing it costs ~2 ms that every one-shot
``-o json`` from cron would pay.  A poll writes many: ``json_line`` uses json's C
encoder, made once, and ``Polls`` keeps what the polls of one read share.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from json import JSONEncoder

import math
from typing import TextIO

from mbtool.cli.results import (
    Listing,
    Points,
    Report,
    Result,
    as_dict,
    engineering_unit,
    points_dict,
    report_dict,
)
from mbtool.cli.sinks.plain import Polls as PlainPolls
from mbtool.cli.sinks.plain import Rows as PlainRows
from mbtool.errors import PartialRead, exit_code_for


def render(result: Result | Report | Points, out: TextIO, csv_header: bool = True) -> None:
    out.write(to_json(data_of(result)) + "\n")


def data_of(result: Result | Report | Points | Listing) -> object:
    """A result as the plain data of its JSON object."""
    if isinstance(result, Listing):
        return result.data()
    if isinstance(result, Points):
        return points_dict(result)
    if isinstance(result, Report):
        return report_dict(result)
    return as_dict(result)


def to_json(value: object) -> str:
    """JSON text of plain data (dict, list, tuple, str, int, float, bool, None).

    Not the json module: importing it costs ~2 ms (its decoder too) that every
    one-shot ``-o json`` from cron would pay; strings are escaped by the same C
    function json itself uses.
    """
    from _json import encode_basestring_ascii  # noqa: PLC0415 - 0.2 ms: -o json only; all commands load this

    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "null"  # NaN and infinities are not JSON; jq would choke on them
    if value is True:
        return "true"
    if value is False:
        return "false"
    if isinstance(value, int | float):
        return repr(value)
    if isinstance(value, str):
        return encode_basestring_ascii(value)
    if isinstance(value, dict):
        return (
            "{"
            + ", ".join(f"{encode_basestring_ascii(str(k))}: {to_json(v)}" for k, v in value.items())
            + "}"
        )
    if isinstance(value, list | tuple):
        return "[" + ", ".join(to_json(item) for item in value) + "]"
    raise TypeError(f"cannot write {type(value).__name__} as JSON")


def error_json(message: str, code: int, **first: object) -> str:
    """The object -o json writes for a failure, one-shot or a poll's: {"error", "exit_code"}."""
    return to_json({**first, "error": message, "exit_code": code})


def json_line(data: dict) -> str:
    """A poll's JSON line, by the json module's C encoder: a sustained poll spends more on
    JSON than on Modbus with to_json, and json's import is nothing to a loop.  The same text, since
    to_json keeps json's separators; NaN and infinities, which json would write as
    invalid JSON, go the to_json way (null)."""
    global _ENCODER
    if _ENCODER is None:
        import json  # noqa: PLC0415 - 1 ms: polling only

        # Made once (json.dumps makes one a call); a poll's data has no cycles to look for.
        _ENCODER = json.JSONEncoder(allow_nan=False, check_circular=False)
    try:
        return _ENCODER.encode(data) + "\n"
    except ValueError:
        return to_json(data) + "\n"


_ENCODER: JSONEncoder | None = None  # made by the first json_line


def _encoded(values: list) -> str:
    """Values as JSON text, by json's C encoder (json_line made it); NaN and the infinities
    as to_json's null."""
    assert _ENCODER is not None
    try:
        return _ENCODER.encode(values)
    except ValueError:
        return to_json(values)


_MARK = "\x00mbtool\x00"  # stands for a field while the line around it is encoded
_MARKED = '"\\u0000mbtool\\u0000"'  # the mark as JSON text (json's C encoder and to_json alike)


def _after_time(data: dict) -> str:
    """A poll's JSON line from just after its time's text on: the time's closing quote, then
    ``data``'s keys."""
    return '"' + json_line({"time": _MARK, **data}).split(_MARKED, 1)[1]


_INT_ARRAYS: dict[int, str] = {}  # the number of ints -> the format that writes them


def _int_form(count: int) -> str:
    """The %-format of ``count`` ints as a JSON array writes them ("[1, -2, 3]", as json and
    repr do): made once a length, where repr formats each int through a call of its own."""
    form = _INT_ARRAYS.get(count)
    if form is None:
        form = _INT_ARRAYS[count] = "[" + ", ".join(["%d"] * count) + "]"
    return form


class PlantPolls:
    """poll -o json: an object a line, a device poll or a change of state."""

    measured = False  # --measurement names its measurement
    exposes = False

    def __init__(self, out, csv_header: bool, measurement: str, labels: dict | None = None) -> None:
        self.out = out
        self.labels = labels or {}  # [poll] site and instance (a fleet's): keys of every record

    def poll(self, poll, when: str) -> None:
        self.out.write(to_json(poll_record(poll, when, self.labels)) + "\n")

    def event(self, event, when: str) -> None:
        self.out.write(to_json(event_record(event, when, self.labels)) + "\n")


def event_record(event, when: str, labels: dict) -> dict:
    """A change of state (plant.schedule.Event) as poll -o json's object, and MQTT's event
    message: its time, the fleet's labels, the new state, the device or link, why, and when it
    is tried again."""
    record = {"time": when, **labels, "event": event.state, event.kind: event.name}
    if event.reason:
        record["reason"] = event.reason
    if event.retry_in is not None:
        record["retry_in"] = event.retry_in
    return record


def poll_record(poll, when: str, fleet: dict | None = None) -> dict:
    """A device poll (plant.schedule.Poll) as poll -o json's object; ``fleet``'s labels (the
    device's tags carry them) keys of their own."""
    device = poll.device
    tags = dict(device.tags or {})
    labels = {key: tags.pop(key) for key in fleet or () if key in tags}
    record = {"time": when, **labels, "device": device.name, "tags": tags, "unit": device.unit}
    if device.groups:  # a poll of one of its groups (issue 44): that group's points alone
        record["group"] = poll.group
    if poll.readings is None:
        record["state"] = poll.state
        record["error"] = str(poll.error)
        record["exit_code"] = int(exit_code_for(poll.error))
        return record
    points, failed = [], []
    for reading in poll.readings:
        point = reading.point
        if reading.error is None:
            entry = {
                "name": point.name,
                "value": reading.value,
                **engineering_unit(point.unit),
                "ref": point.ref,
            }
            if reading.value is None:
                entry["invalid"] = True  # the device sent a value its map says means no data
            points.append(entry)
        else:
            failed.append({"name": point.name, "ref": point.ref, "error": reading.error.answer})
    record["state"] = poll.state
    record["points"] = points
    if failed:
        record["failed"] = failed
    return record


class Log:
    """A stream of items as they are seen: a JSON object a line, flushed (``views.data(item)``;
    None: an item JSON does not carry).  Its objects are the items alone: no server event."""

    events = False

    def __init__(self, out: TextIO, views, **console_options) -> None:
        self.out = out
        self.views = views

    def write(self, item) -> None:
        data = self.views.data(item)
        if data is not None:
            self.out.write(to_json(data) + "\n")
            self.out.flush()


class Rows(PlainRows):
    """A stream of rows (scan's units as they are found): one object at the end."""

    def row(self, cells: list, line: str) -> None:
        pass

    def end(self, listing: Listing) -> None:
        self.out.write(to_json(listing.data()) + "\n")
        self.out.flush()


class Polls(PlainPolls):
    """read --interval -o json: a JSON line a poll, a change or a failed poll.

    A poll's line is the text ``json_line({"time": ..., **as_dict(result)})`` writes of its whole
    result, made with less work a poll: the polls of one read differ only in their time, values
    and raw registers, so the rest of the line (unit, function, name, address, type, addresses,
    refs) is encoded once for them, and a poll's line is one f-string of that text with its time,
    values and registers set in; where the values are ints (an integer type, one order), their
    array is one %-format made once, as the registers' always is."""

    def __init__(self, output) -> None:
        super().__init__(output)  # self.read: the read whose polls the text below is for
        # The line's text around the time, the values and the registers (the last "" when the
        # line has none), and the arrays' %-formats: the values' when they are ints (None: the
        # encoder writes them), the registers' (None: the line has none).
        self.parts: tuple[str, str, str] = ("", "", "")
        self.ints: str | None = None
        self.registers: str | None = None
        # The last values written (or map's points) and their arrays' text: the same again
        # (Deferred's, a reply whose values have not changed) is written with only its time new.
        self.written: list | Points | None = None
        self.values_text = self.raw = ""
        self.points = ""  # a map's points' line, after its time

    def result(self, when: str, result, stamp: float | None = None) -> None:
        """A map's points, or a whole result (--changes' first poll)."""
        if result.__class__ is not Points:
            self.read = self.written = None  # a result of its own: its line is its own
            self.values(when, result, result.values, result.registers, stamp)
            return
        if result is not self.written:  # a map's points: their line, after its time, as it is
            self.written, self.read, self.points = result, None, _after_time(points_dict(result))
        self.output.emit(f'{{"time": "{when}{self.points}')

    def values(self, when: str, read: Result, values: list, registers, stamp: float | None = None) -> None:
        if values is not self.written:
            self.written = values
            if read is not self.read:
                self._learn(read, values, registers)
            ints = self.ints
            try:
                self.values_text = ints % tuple(values) if ints is not None else _encoded(values)
            except TypeError:  # not as many values as the first poll's
                self.values_text = _encoded(values)
            if self.registers is not None:
                self.raw = self.registers % tuple(registers)
        # The time is local_time's digits and punctuation: quoted, it is its JSON string.
        head, middle, tail = self.parts
        self.output.emit(f'{{"time": "{when}{head}{self.values_text}{middle}{self.raw}{tail}')

    def _learn(self, read: Result, values: list, registers) -> None:
        """The line's text for the polls of ``read``, cut where the values and the registers go."""
        from mbtool.codec.values import TYPES  # noqa: PLC0415 - polling only; all commands load this

        data = {**as_dict(read.polled(values, registers)), "values": _MARK}
        shown = data.get("registers")  # the raw registers, when the line has them
        if shown is not None:
            data["registers"] = _MARK
        head, middle, *tail = _after_time(data).split(_MARKED)
        self.read, self.parts = read, (head, middle, tail[0] if tail else "")
        # Registers are always ints, and so are the values of an integer type: their arrays
        # with a %d for each, as json and repr write an int.
        integers = read.extra is None and read.type is not None and TYPES[read.type].integer
        self.ints = _int_form(len(values)) if integers else None
        self.registers = None if shown is None else _int_form(len(shown))
        self.raw = ""

    def change(self, when: str, what: dict, where: str, old, new, unit: str) -> None:
        self.output.emit(json_line({"time": when, **what, "old": old, "new": new, **engineering_unit(unit)}))

    def failure(self, when: str, error: BaseException) -> None:
        if not isinstance(error, PartialRead):
            # jq consumers read stdout only: a failed poll must show up there too (a partial
            # read's line names the points it could not read).
            code = int(exit_code_for(error))
            self.output.emit(error_json(str(error), code, time=when) + "\n")
            self.output.flush()  # at once, as its line on stderr
