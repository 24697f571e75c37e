"""Issue 41.9: the output's share of a sustained poll, from the decoded reply to the line
written (cli.poll_output's Deferred and Output, the format's Polls, the time stamp), counted in
the bytecodes it runs: a count, which a loaded machine does not move as it moves a time.  The
headline poll: 10 holding registers whose values change every read, shown in each format a
pipe is given; each poll's text is checked against the format's own writer of the result."""

from __future__ import annotations

import io
import json
import statistics

from helpers.checks import bytecodes

from mbtool.cli.poll_output import Deferred, Output
from mbtool.cli.results import Result, as_dict
from mbtool.cli.sinks.json import json_line
from mbtool.cli.stamps import local_time
from mbtool.codec.data_access import RegistersResponse
from mbtool.codec.values import value_addresses, value_decoder

SECOND = 1764140800.0  # a poll's time.time(); its polls a millisecond apart, in one second


def _polls(fmt: str, value_type: str = "uint16", polls: int = 40) -> tuple[int, list[str], list[Result]]:
    """``polls`` polls of read-holding-registers 0 10 shown in ``fmt`` as read --interval shows
    them (the reply held while the next request is on its way, then written): the median of the
    bytecodes a poll's output ran, each poll's text, and each poll's result."""
    decode = value_decoder(value_type)
    shared = Result(
        1, 3, "Read Holding Registers", 0, [], value_type, addresses=value_addresses(value_type, 0, 10)
    )

    def to_result(reply):  # read.py's: the shared result with the poll's values
        registers = reply.registers
        return shared.again(decode(registers), registers)

    out = io.StringIO()
    shown = Deferred(Output(fmt, out), to_result)
    counts, texts, results = [], [], []
    for poll in range(polls):
        reply = RegistersResponse(3, tuple((poll * 7 + i * 1009) % 65536 for i in range(10)))
        before = out.tell()

        def show(when=SECOND + poll / 1000, reply=reply) -> None:
            shown.hold(when, reply)
            shown.write()

        counts.append(bytecodes(show))
        shown.output.flush()  # the polls' writes joined (Output.emit): written here, uncounted
        texts.append(out.getvalue()[before:])
        results.append(to_result(reply))
    return int(statistics.median(counts[1:])), texts, results


def test_a_json_poll_is_written_in_few_bytecodes_and_is_the_line_json_writes():
    ran, texts, results = _polls("json")
    for poll, (text, result) in enumerate(zip(texts, results, strict=True)):
        assert text == json_line({"time": local_time(SECOND + poll / 1000), **as_dict(result)})
        assert json.loads(text)["values"] == result.values
    assert ran <= 210, f"a -o json poll's output ran {ran} bytecodes"
