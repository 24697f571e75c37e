"""-o json's poll lines (sinks.json.Polls), made with less work a
poll, are the very text json_line writes of the whole result: whatever the type, the values and
the shape of the poll."""

from __future__ import annotations

import io
import json
import math
from operator import attrgetter

from mbtool.cli.poll_output import DeferredRead, Output
from mbtool.cli.results import PointRow, Points, PollsOfRead, Result, as_dict, points_dict
from mbtool.cli.sinks.json import json_line
from mbtool.codec.data_access import RegistersResponse
from mbtool.codec.values import value_decoder

WHEN = "2026-11-28T23:51:57.580+01:00"


def _poll_of(shared: Result, values: list, registers: tuple[int, ...] | None = None) -> Result:
    """A poll's result of ``shared``'s read: ``values``, and ``registers`` as read."""
    return shared.polled(values, registers)


def _written(output: Output, when: str, result) -> str:
    """What a poll's result adds to -o json's output."""
    before = output.out.tell()
    output.result(when, result)
    output.flush()
    return output.out.getvalue()[before:]


def _result(value_type: str, registers: tuple[int, ...], **fields) -> Result:
    values = value_decoder(value_type)(registers)
    return Result(1, 3, "Read Holding Registers", 0, values, value_type, registers, **fields)


def test_each_poll_line_is_the_line_json_writes_of_its_result():
    shared = Result(
        7, 4, "Read Input Registers", 100, [], "int32", refs=["30101", "30103"], addresses=[100, 102]
    )
    results = [
        _result("uint16", (1, 2, 3)),
        _result("uint16", (4, 5, 6)),  # the same shape, other values
        _result("uint16", (1, 2)),  # fewer values: another shape
        _result("int16", (65535, 1)),  # registers shown beside the values
        _poll_of(shared, [-1, 65537], (65535, 65535, 1, 1)),
        _poll_of(shared, [7, 8], (0, 7, 0, 8)),
        _result("float32", (0x3F80, 0, 0x7FC0, 0)),  # 1.0 and NaN: null, as to_json writes it
        _result("float32", (0x3F80, 0, 0x4000, 0)),
        _result("string", (0x4142, 0x4300)),
        Result(1, 1, "Read Coils", 0, [True, False, True]),  # bits: true and false, not 1 and 0
        Result(1, 3, "100% Read", 0, [5], "uint16", (5,)),  # a % in the text around the values
        _result("uint16", (9, 9, 9), extra={"order": "all"}),
        Result(1, 3, "Read Holding Registers", 0, [1.5, math.inf], "float32", (1, 2, 3, 4)),
    ]
    output = Output("json", io.StringIO())
    for result in results:
        line = _written(output, WHEN, result)
        assert line == json_line({"time": WHEN, **as_dict(result)}), result
        data = json.loads(line)
        assert data["time"] == WHEN and data["values"] == [
            None if isinstance(v, float) and not math.isfinite(v) else v for v in result.values
        ]


def _values_written(output: Output, when: str, read: Result, values: list, registers) -> str:
    """What a poll of ``read`` (its values, as DeferredRead hands them) adds to -o json's output."""
    before = output.out.tell()
    output.values(when, read, values, registers)
    output.flush()
    return output.out.getvalue()[before:]


def test_the_polls_of_one_read_and_a_maps_points_are_the_lines_json_writes():
    """Polls of one read are handed to the output as their read and values: the text around
    their values is kept for them, and another read, or a map's points, have their own; each
    line is the one json_line writes of the poll's whole result (Result.polled)."""
    shared = Result(
        7, 3, "Read Holding Registers", 10, [], "int16", refs=["40011", "40012"], addresses=[10, 11]
    )
    other = Result(7, 3, "Read Holding Registers", 10, [], "int16", addresses=[10, 11])
    points = Points(7, "pump.toml", [PointRow("level", 2.5, "m", "40001", (25,), False)])
    bits = Result(7, 1, "Read Coils", 0, [], addresses=[0, 1])
    output = Output("json", io.StringIO())
    same = [2, 3]
    for read, values, registers in (
        (shared, [1, -1], (1, 65535)),
        (shared, same, (2, 3)),
        (shared, same, (2, 3)),  # the same values again (a reply seen before): only the time new
        (other, [4, 5], (4, 5)),
        (bits, [True, False], None),
    ):
        expected = json_line({"time": WHEN, **as_dict(read.polled(values, registers))})
        assert _values_written(output, WHEN, read, values, registers) == expected
    assert _written(output, WHEN, points) == json_line({"time": WHEN, **points_dict(points)})
    assert _values_written(output, WHEN, shared, [6, 7], (6, 7)).startswith(
        '{"time": "' + WHEN + '", "unit": 7'
    )


def test_a_poll_s_result_is_its_read_s_with_the_poll_s_values_and_shares_the_rest():
    shared = Result(7, 3, "Read Holding Registers", 10, [], "uint16", refs=["40011"], addresses=[10])
    again = _poll_of(shared, [5], (5,))
    assert again == Result(
        7, 3, "Read Holding Registers", 10, [5], "uint16", (5,), refs=["40011"], addresses=[10]
    )
    assert again.addresses is shared.addresses and shared.values == []


def test_the_same_result_again_is_written_with_only_its_time_new():
    output = Output("json", io.StringIO())
    result = _result("int16", (65535, 2))
    first, again = _written(output, WHEN, result), _written(output, WHEN.replace("57.580", "58.000"), result)
    assert (
        again
        == first.replace("57.580", "58.000")
        == json_line({"time": WHEN.replace("57.580", "58.000"), **as_dict(result)})
    )


def test_a_reply_shown_again_by_a_read_is_decoded_once_and_written_with_its_own_time():
    """The client hands back the same response for the same reply bytes: DeferredRead decodes
    it once, and each poll's line still carries that poll's time."""
    decoded = []

    def decode(registers):
        decoded.append(registers)
        return list(registers)

    read = Result(1, 3, "Read Holding Registers", 10, [], "uint16", addresses=[10, 11])
    output = Output("json", io.StringIO())
    shown = DeferredRead(output, PollsOfRead(read, attrgetter("registers"), decode, True))
    same, changed = RegistersResponse(3, (5, 6)), RegistersResponse(3, (7, 6))
    for when, reply in [(1.0, same), (2.0, same), (3.0, changed), (4.0, same)]:
        shown.hold(1_700_000_000 + when, reply)
        shown.write()
    shown.close()
    assert decoded == [(5, 6), (7, 6), (5, 6)]
    lines = [json.loads(line) for line in output.out.getvalue().splitlines()]
    assert [line["values"] for line in lines] == [[5, 6], [5, 6], [7, 6], [5, 6]]
    assert [line["time"][17:23] for line in lines] == ["21.000", "22.000", "23.000", "24.000"]
    assert all(line["addresses"] == [10, 11] for line in lines)
