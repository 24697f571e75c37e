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

from mbtool.cli.results import Listing, Points, Report, Result, as_dict, points_dict, report_dict
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
    refs) is encoded once and kept while the result's shape stays the same; and a poll
    whose result is the one before (its values unchanged: ``Deferred``) writes only its
    time anew."""

    def __init__(self) -> None:
        self.shape: tuple | None = None
        self.parts: list[str] = []  # the text around the time, the values and the registers
        self.integers = False  # the values are ints (an integer type, one order)
        self.result = None  # the last result written,
        self.rest: str | None = None  # and its line after the time (None: it holds a NaN)

    def line(self, when: str, result) -> str:
        if result is not self.result:
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
            self.shape, self.parts = shape, self._parts(result)
            from mbtool.codec.values import TYPES  # noqa: PLC0415 - polling only; all commands load this

            self.integers = result.extra is None and result.type is not None and TYPES[result.type].integer
        # Registers are always ints, and so are the values of an integer type: written by a
        # format of their own (_int_array).  Other values (floats that may be NaN, strings,
        # bits) take the encoder.
        values = result.values
        encoder = _ENCODER
        assert encoder is not None  # json_line made it, for the line's parts
        try:
            text = _int_array(values) if self.integers and type(values) is list else encoder.encode(values)
        except ValueError:
            return None
        parts = self.parts
        if len(parts) == 3:
            return parts[1] + text + parts[2]
        return parts[1] + text + parts[2] + _int_array(result.registers) + parts[3]

    @staticmethod
    def _parts(result) -> list[str]:
        """The line's text, cut where the time, the values and the registers go."""
        data = {"time": _MARK, **as_dict(result), "values": _MARK}
        if "registers" in data:
            data["registers"] = _MARK
        text = json_line(data)
        assert _ENCODER is not None  # json_line made it
        return text.split(_ENCODER.encode(_MARK))


_MARK = "\x00mbtool\x00"  # stands for a field while the line around it is encoded

_INT_ARRAYS: dict[int, str] = {}  # the number of ints -> the format that writes them


def _int_array(numbers) -> str:
    """Ints as a JSON array writes them ("[1, -2, 3]", as json and repr do): one %-format for
    the whole array, made once a length, where repr formats each int through a call of its
    own (half the instructions a poll for ten registers)."""
    count = len(numbers)
    form = _INT_ARRAYS.get(count)
    if form is None:
        form = _INT_ARRAYS[count] = "[" + ", ".join(["%d"] * count) + "]"
    return form % tuple(numbers)


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
            # A point's "unit" is its engineering unit, left out when it has none: the
            # record's own "unit" is the device's unit id.
            engineering = {"unit": point.unit} if point.unit else {}
            entry = {"name": point.name, "value": reading.value, **engineering, "ref": point.ref}
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
        engineering = {"unit": unit} if unit else {}
        self.output.emit(json_line({"time": when, **what, "old": old, "new": new, **engineering}))

    def failure(self, when: str, error: BaseException) -> None:
        if not isinstance(error, PartialRead):
            # jq consumers read stdout only: a failed poll must show up there too (a partial
            # read's line names the points it could not read).
            code = int(exit_code_for(error))
            self.output.emit(error_json(str(error), code, time=when) + "\n", now=True)
