"""-o json's poll lines (sinks.json.JsonLines), made with less work a poll, are the very text
json_line writes of the whole result: whatever the type, the values and the shape of the poll."""

from __future__ import annotations

import json
import math

from mbtool.cli.results import Result, as_dict
from mbtool.cli.sinks.json import JsonLines, json_line
from mbtool.codec.values import value_decoder

WHEN = "2026-11-28T23:51:57.580+01:00"


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
        shared.again([-1, 65537], (65535, 65535, 1, 1)),
        shared.again([7, 8], (0, 7, 0, 8)),
        _result("float32", (0x3F80, 0, 0x7FC0, 0)),  # 1.0 and NaN: null, as to_json writes it
        _result("float32", (0x3F80, 0, 0x4000, 0)),
        _result("string", (0x4142, 0x4300)),
        Result(1, 1, "Read Coils", 0, [True, False, True]),  # bits: true and false, not 1 and 0
        Result(1, 3, "100% Read", 0, [5], "uint16", (5,)),  # a % in the text around the values
        _result("uint16", (9, 9, 9), extra={"order": "all"}),
    ]
    lines = JsonLines()
    for result in results:
        line = lines.line(WHEN, result)
        assert line == json_line({"time": WHEN, **as_dict(result)}), result
        data = json.loads(line)
        assert data["time"] == WHEN and data["values"] == [
            None if isinstance(v, float) and math.isnan(v) else v for v in result.values
        ]


def test_again_is_the_result_with_the_polls_values_and_shares_the_rest():
    shared = Result(7, 3, "Read Holding Registers", 10, [], "uint16", refs=["40011"], addresses=[10])
    again = shared.again([5], (5,))
    assert again == Result(
        7, 3, "Read Holding Registers", 10, [5], "uint16", (5,), refs=["40011"], addresses=[10]
    )
    assert again.addresses is shared.addresses and shared.values == []


def test_the_same_result_again_is_written_with_only_its_time_new():
    lines = JsonLines()
    result = _result("int16", (65535, 2))
    first, again = lines.line(WHEN, result), lines.line(WHEN.replace("57.580", "58.000"), result)
    assert (
        again
        == first.replace("57.580", "58.000")
        == json_line({"time": WHEN.replace("57.580", "58.000"), **as_dict(result)})
    )
