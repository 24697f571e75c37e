"""Issue 41.9: the output's share of a sustained poll, from the decoded reply to the line
written (cli.poll_output's Deferred and Output, the format's Polls, the time stamp), counted in
the bytecodes it runs: a count, which a loaded machine does not move as it moves a time.  The
headline poll: 10 holding registers whose values change every read, shown in each format a
pipe is given; each poll's text is checked against the format's own writer of the result.

The measure is callgrind's instructions (bench/polling_instructions.py), which a test cannot
take on every machine; bytecodes are their proxy here, and some cuts trade a few bytecodes for
fewer instructions in C (a poll's Result copies a table whole, -o json formats only the arrays,
plain and CSV are a %-format and a replace, not a str.format, Deferred reads the functions it
holds as attributes before it calls them: 7 bytecodes more, some 500 instructions fewer):
main before issue 41.9's cuts ran 276, 638 and 1903; 234, 200 and 215 before a poll's reply
became its result in one call (Result.poll_results, made once a read: 232, 198 and 213); 198, 165
and 182 since a read's poll is handed to the output as its read and values (DeferredRead), no
Result made a poll."""

from __future__ import annotations

import csv
import io
import json
import statistics
import sys
from operator import attrgetter
from pathlib import Path

import pytest
from helpers.checks import bytecodes, in_fresh_interpreter, unspecialized

import mbtool
from mbtool.cli import poll_output
from mbtool.cli.poll_output import DeferredRead, Output
from mbtool.cli.results import PointRow, Points, PollsOfRead, Result, as_dict
from mbtool.cli.sinks.csv import rows_of
from mbtool.cli.sinks.json import json_line
from mbtool.cli.sinks.plain import text as plain_text
from mbtool.cli.stamps import local_time
from mbtool.codec.data_access import RegistersResponse
from mbtool.codec.values import value_addresses, value_decoder

MBTOOL = str(Path(mbtool.__file__).parent)
SECOND = 1764140800.0  # a poll's time.time(); its polls a millisecond apart, in one second


def _polls(fmt: str, monkeypatch, polls: int = 40) -> tuple[int, list[str], list[Result]]:
    """``polls`` polls of read-holding-registers 0 10 shown in ``fmt`` as read --interval shows
    them (the reply held while the next request is on its way, then written): the median of the
    bytecodes a poll's output ran, each poll's text, and each poll's result.  The test writes
    the polls' joined text itself, uncounted: a loaded machine's slow poll is not one that
    flushes."""
    monkeypatch.setattr(poll_output, "FLUSH_GAP", 3600.0)
    to_result = _to_result()
    out = io.StringIO()
    shown = DeferredRead(Output(fmt, out), to_result)
    counts, texts, results = [], [], []
    for poll in range(polls):
        reply = _reply(poll)
        before = out.tell()

        def show(when=SECOND + poll / 1000, reply=reply) -> None:
            shown.hold(when, reply)
            shown.write()

        counts.append(bytecodes(show))
        shown.output.flush()
        texts.append(out.getvalue()[before:])
        results.append(to_result(reply))
    return int(statistics.median(counts[1:])), texts, results


def _to_result() -> PollsOfRead:
    """read.py's polls of read-holding-registers 0 10: the shared result and how a reply's values are decoded."""
    decode = value_decoder("uint16")
    shared = Result(
        1, 3, "Read Holding Registers", 0, [], "uint16", addresses=value_addresses("uint16", 0, 10)
    )

    return PollsOfRead(shared, attrgetter("registers"), decode, True)


def _reply(poll: int) -> RegistersResponse:
    """The reply to poll number ``poll``: every value new."""
    return RegistersResponse(3, tuple((poll * 7 + i * 1009) % 65536 for i in range(10)))


def _unspecialized() -> list[str]:
    """The attribute reads of mbtool's a -o json poll's output left generic (run in a fresh
    interpreter)."""
    poll_output.FLUSH_GAP = 3600.0  # this interpreter's own: no flush among the polls
    shown = DeferredRead(Output("json", io.StringIO()), _to_result())
    polls = iter(range(10**6))

    def show() -> None:
        poll = next(polls)
        shown.hold(SECOND + poll / 1000, _reply(poll))
        shown.write()

    return unspecialized(show, MBTOOL)


# What 3.11 specializes (the bench's interpreter): 3.12 specializes more.
@pytest.mark.skipif(sys.version_info[:2] != (3, 11), reason="what is specialized is 3.11's")
def test_every_attribute_a_poll_s_output_reads_is_one_the_interpreter_specializes():
    """A poll's result (Result.poll_results) copied the table its read's result's __dict__ made, which
    shares its keys with the class (split): 3.11 reads an attribute of a split table the generic
    way, and the sink's reads of its values and shared result were generic every poll (some 400
    instructions a poll of read --interval -o json, callgrind)."""
    assert in_fresh_interpreter("cli.test_poll_cost", "_unspecialized") == []


def test_a_json_poll_is_written_in_few_bytecodes_and_is_the_line_json_writes(monkeypatch):
    ran, texts, results = _polls("json", monkeypatch)
    for poll, (text, result) in enumerate(zip(texts, results, strict=True)):
        assert text == json_line({"time": local_time(SECOND + poll / 1000), **as_dict(result)})
        assert json.loads(text)["values"] == result.values
    assert ran <= 199, f"a -o json poll's output ran {ran} bytecodes"


@pytest.mark.parametrize("fmt", ["plain", "csv"])
def test_a_plain_or_csv_poll_is_written_in_few_bytecodes(fmt, monkeypatch):
    ran, texts, results = _polls(fmt, monkeypatch)
    for poll, (text, result) in enumerate(zip(texts, results, strict=True)):
        when = local_time(SECOND + poll / 1000)
        sep = " " if fmt == "plain" else ","
        rows = "".join(
            f"{when}{sep}{a}{sep}{v}\n" for a, v in zip(result.addresses, result.values, strict=True)
        )
        assert text == ("time,address,value\n" if fmt == "csv" and poll == 0 else "") + rows
    assert ran <= {"plain": 166, "csv": 183}[fmt], f"a -o {fmt} poll's output ran {ran} bytecodes"


def _shapes() -> list[Result | Points]:
    """Polls of every shape a read gives: each type, bits, --order all, references, a map."""

    def read(value_type: str, registers: tuple[int, ...], **fields) -> Result:
        shared = Result(
            1,
            3,
            "Read Holding Registers",
            7,
            [],
            value_type,
            addresses=value_addresses(value_type, 7, len(registers)),
            **fields,
        )
        return _poll_of(shared, value_decoder(value_type)(registers), registers)

    bits = Result(1, 1, "Read Coils", 0, [], addresses=[0, 1, 2])
    all_orders = Result(1, 3, "Read Holding Registers", 0, [], "int32", extra={"order": "all"}, addresses=[0])
    return [
        read("uint16", (1, 2, 65535)),
        read("int16", (65535, 1), refs=["40008", "40009"]),
        read("float32", (0x3F80, 0, 0x7FC0, 0, 0x7F80, 0, 0x3DCC, 0xCCCD)),  # 1.0, NaN, inf, 0.1
        read("string", (0x612C, 0x227B, 0x7D00)),  # a,"{}: quoted in CSV, braces as they are
        read("hex", (0x00FF, 0x1234)),
        _poll_of(bits, [True, False, True]),
        _poll_of(all_orders, [{"ABCD": 1, "CDAB": 65536}], (0, 1)),
        Points(1, "pump.toml", [PointRow("level", 2.5, "m", "40001", (25,), False)]),
    ]


def _poll_of(shared: Result, values: list, registers: tuple[int, ...] | None = None) -> Result:
    """A poll's result of ``shared``'s read: ``values``, and ``registers`` as read."""
    return shared.polled(values, registers)


@pytest.mark.parametrize("fmt", ["plain", "csv"])
def test_a_poll_of_every_shape_is_the_text_the_formats_own_writer_writes(fmt):
    when = local_time(SECOND)
    for result in _shapes():
        out = io.StringIO()
        output = Output(fmt, out, csv_header=False)
        for _ in range(2):  # the first poll of a read, and one after
            output.result(when, result)
        output.flush()
        if fmt == "plain":
            expected = plain_text(result, when)
        else:
            written = io.StringIO()
            header, rows = rows_of(result)
            csv.writer(written, lineterminator="\n").writerows([when, *row] for row in rows)
            expected = written.getvalue()
        assert out.getvalue() == 2 * expected, result
