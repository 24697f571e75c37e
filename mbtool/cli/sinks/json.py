"""-o json, and JSON text: the one writer of it in the CLI, for every object a command prints.

One rule for all: json's separators, and NaN and the infinities as null (they are no
JSON; jq would choke on them).  One object (a one-shot read, an error) is written by
``to_json``, without the json module: importing it costs ~2 ms that every one-shot
``-o json`` from cron would pay.  A poll writes many: ``json_line`` uses json's C
encoder, made once, and ``JsonLines`` keeps what a command's polls share.
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


class JsonLines:
    """A poll's JSON line, as ``json_line({"time": ..., **as_dict(result)})`` writes it, with
    less work a poll: the polls of one command differ only in their time, values and raw
    registers, so the rest of the line (unit, function, name, address, type, addresses,
    refs) is encoded once and kept while the result's shape stays the same; where the values
    are ints (an integer type, one order), what follows the time is one %-format made once,
    filled with the values and the registers in one call; and a poll whose result is the one
    before (its values unchanged: ``Deferred``) writes only its time anew."""

    def __init__(self) -> None:
        self.shape: tuple | None = None
        self.parts: list[str] = []  # the text around the time, the values and the registers
        # The line after the time as a %-format when the values are ints (None: they take the
        # encoder), for how many values and registers; and whether the registers are in it.
        self.ints: str | None = None
        self.counts = (0, 0)
        self.registers = False
        self.result = None  # the last result written,
        self.rest: str | None = None  # and its line after the time (None: it holds a NaN)

    def line(self, when: str, result) -> str:
        if result is not self.result:  # else the poll before's values (Deferred): only the time is new
            self.result, self.rest = result, self._rest(result)
        if self.rest is None:  # NaN or an infinity: to_json's null, through the whole dict
            return json_line({"time": when, **as_dict(result)})
        # The time is local_time's digits and punctuation: quoted, it is its JSON string.
        return f'{self.parts[0]}"{when}"{self.rest}'

    def _rest(self, result) -> str | None:
        """The line after the time: the values and registers within the text kept for the shape."""
        shape = (
            result.unit,
            result.function,
            result.name,
            result.address,
            result.addresses,
            result.type,
            result.refs,
            result.extra,
            result.registers is None,
        )
        if shape != self.shape:
            self._learn(shape, result)
        values = result.values
        ints = self.ints
        if ints is not None and type(values) is list and len(values) == self.counts[0]:
            if not self.registers:
                return ints % tuple(values)
            registers = result.registers
            if len(registers) == self.counts[1]:
                return ints % (*values, *registers)
        encoder = _ENCODER
        assert encoder is not None  # json_line made it, for the line's parts
        try:
            text = encoder.encode(values)
        except ValueError:
            return None
        parts = self.parts
        if self.registers:
            return f"{parts[1]}{text}{parts[2]}{_int_array(result.registers)}{parts[3]}"
        return f"{parts[1]}{text}{parts[2]}"

    def _learn(self, shape: tuple, result) -> None:
        """The line's text for results of this shape, cut where the time, the values and the
        registers go."""
        from mbtool.codec.values import TYPES  # noqa: PLC0415 - polling only; all commands load this

        data = {"time": _MARK, **as_dict(result), "values": _MARK}
        self.registers = "registers" in data
        if self.registers:
            data["registers"] = _MARK
        text = json_line(data)
        assert _ENCODER is not None  # json_line made it
        self.shape, self.parts = shape, text.split(_ENCODER.encode(_MARK))
        integers = result.extra is None and result.type is not None and TYPES[result.type].integer
        if not integers:
            self.ints = None
            return
        # Registers are always ints, and so are the values of an integer type: the line's
        # text with a %d for each, as json and repr write an int.
        part = [piece.replace("%", "%%") for piece in self.parts]
        values, registers = len(result.values), len(result.registers) if self.registers else 0
        self.ints = f"{part[1]}{_int_form(values)}{part[2]}"
        if self.registers:
            self.ints += f"{_int_form(registers)}{part[3]}"
        self.counts = (values, registers)


_MARK = "\x00mbtool\x00"  # stands for a field while the line around it is encoded

_INT_ARRAYS: dict[int, str] = {}  # the number of ints -> the format that writes them


def _int_form(count: int) -> str:
    """The %-format of ``count`` ints as a JSON array writes them ("[1, -2, 3]", as json and
    repr do): made once a length, where repr formats each int through a call of its own."""
    form = _INT_ARRAYS.get(count)
    if form is None:
        form = _INT_ARRAYS[count] = "[" + ", ".join(["%d"] * count) + "]"
    return form


def _int_array(numbers) -> str:
    """Ints as a JSON array writes them, in one %-format."""
    return _int_form(len(numbers)) % tuple(numbers)


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
    """read --interval -o json: a JSON line a poll, a change or a failed poll."""

    def __init__(self, output) -> None:
        super().__init__(output)
        self.lines = JsonLines()

    def result(self, when: str, result, stamp: float | None = None) -> None:
        if result.__class__ is Points:
            self.output.emit(json_line({"time": when, **points_dict(result)}))
        else:
            self.output.emit(self.lines.line(when, result))

    def change(self, when: str, what: dict, where: str, old, new, unit: str) -> None:
        self.output.emit(json_line({"time": when, **what, "old": old, "new": new, **engineering_unit(unit)}))

    def failure(self, when: str, error: BaseException) -> None:
        if not isinstance(error, PartialRead):
            # jq consumers read stdout only: a failed poll must show up there too (a partial
            # read's line names the points it could not read).
            code = int(exit_code_for(error))
            self.output.emit(error_json(str(error), code, time=when) + "\n", now=True)
