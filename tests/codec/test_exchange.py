"""The judgement of a reply, sans-IO: bytes in, the reply or the most telling problem out.

No clock and no link: each case feeds an ``Exchange`` the bytes a device would send and
says when the line paused or went quiet, as the client does (tests/link/test_client.py
drives the same cases through the client, with time).
"""

from __future__ import annotations

import pytest

from mbtool.codec.ascii import AsciiFramer
from mbtool.codec.checksum import crc_bytes
from mbtool.codec.data_access import ReadCoils, ReadHoldingRegisters, ReadInputRegisters, WriteSingleRegister
from mbtool.codec.errors import ChecksumError, FrameError, MismatchError, ModbusException
from mbtool.codec.exchange import KNOWN_REQUESTS, Exchange, Trace, worse
from mbtool.codec.mbap import TcpFramer
from mbtool.codec.pdu import ExceptionResponse
from mbtool.codec.raw import RawRequest
from mbtool.codec.rtu import RtuFramer


def rtu(hex_text: str) -> bytes:
    body = bytes.fromhex(hex_text)
    return body + crc_bytes(body)


REQUEST = ReadHoldingRegisters(0x6B, 3)
SENT = rtu("11 03 00 6B 00 03")
REPLY = rtu("11 03 06 02 2B 00 00 00 64")  # seed 002 fig. 15
REPLY_PDU = bytes.fromhex("03 06 02 2B 00 00 00 64")


class Notes(Trace):
    def __init__(self) -> None:
        self.lines: list[tuple] = []

    def received(self, adu: bytes, note: str = "") -> None:
        self.lines.append(("received", adu, note))

    def rejected(self, data: bytes, error: FrameError) -> None:
        self.lines.append(("rejected", data, str(error)))


def serial(**options) -> Exchange:
    return Exchange(RtuFramer(), watch_echo=True, **options)


def tcp(**options) -> Exchange:
    return Exchange(TcpFramer(), **options)


def started(exchange: Exchange, request=REQUEST, unit: int = 0x11) -> bytes:
    return exchange.attempt(unit, request, fresh=True)


def test_the_attempt_is_the_request_framed_and_its_reply_is_decoded():
    exchange = serial()
    assert started(exchange) == SENT
    assert exchange.receive(REPLY).registers == (555, 0, 100)


def test_a_reply_dripped_byte_by_byte_is_found_at_its_last_byte():
    exchange = serial()
    started(exchange)
    found = [exchange.receive(bytes([b])) for b in REPLY]
    assert found[:-1] == [None] * (len(REPLY) - 1)
    assert found[-1].registers == (555, 0, 100)


def test_noise_before_the_reply_is_traced_as_rejected_and_skipped():
    notes = Notes()
    exchange = serial(trace=notes)
    started(exchange)
    assert exchange.receive(b"\x00\xff\x11") is None
    assert exchange.receive(REPLY).registers == (555, 0, 100)
    assert notes.lines[0][0] == "rejected"


def test_silence_leaves_no_problem_for_the_client_to_call_a_timeout():
    exchange = serial()
    started(exchange)
    assert exchange.receive(b"") is None
    assert exchange.close() is None and exchange.problem is None


def test_a_bad_crc_settles_at_once_and_is_the_problem():
    exchange = serial()
    started(exchange)
    assert exchange.receive(REPLY[:-1] + bytes([REPLY[-1] ^ 0xFF])) is None
    assert exchange.settling, "a complete bad frame with nothing after it: wait only a little"
    assert exchange.close() is None
    assert isinstance(exchange.problem, ChecksumError)


def test_a_good_reply_after_a_bad_crc_is_still_the_reply():
    exchange = serial()
    started(exchange)
    assert exchange.receive(REPLY[:-1] + bytes([REPLY[-1] ^ 0xFF])) is None
    assert exchange.receive(REPLY).registers == (555, 0, 100)


def test_a_reply_from_another_unit_is_discarded_and_named():
    notes = Notes()
    exchange = serial(trace=notes)
    started(exchange)
    other = rtu("12 03 06 02 2B 00 00 00 64")
    assert exchange.receive(other) is None
    assert exchange.close() is None
    assert isinstance(exchange.problem, MismatchError)
    assert "reply from unit 18, expected unit 17, discarded" in str(exchange.problem)
    assert notes.lines == [("received", other, "reply from unit 18, expected unit 17")]


def test_rtu_a_reply_of_our_unit_that_does_not_fit_is_a_late_one_and_discarded():
    exchange = serial()
    started(exchange)
    assert exchange.receive(rtu("11 03 04 00 0A 00 0B")) is None
    assert exchange.receive(REPLY).registers == (555, 0, 100)


def test_an_exception_reply_is_the_reply():
    exchange = serial()
    started(exchange)
    reply = exchange.receive(rtu("11 83 02"))
    assert isinstance(reply, ExceptionResponse) and reply.exception_code == 2


def test_tcp_a_reply_with_another_transaction_id_is_discarded_and_ours_taken():
    notes = Notes()
    exchange = tcp(trace=notes)
    started(exchange)
    framer = TcpFramer()
    old = framer.build(0x11, REPLY_PDU, 7)
    assert exchange.receive(old + framer.build(0x11, REPLY_PDU, 1)).registers == (555, 0, 100)
    assert notes.lines[0] == ("received", old, "reply has transaction id 7, expected 1")
    assert exchange.answered_id == 1


def test_tcp_the_reply_predicted_is_taken_as_the_parse_would_take_it_and_anything_else_is_parsed():
    """The first read after the request is nearly always exactly the reply asked for: taken
    without the framer; a reply in two reads, or behind other bytes, goes to the parse."""
    reply = TcpFramer().build(0x11, REPLY_PDU, 1)
    notes = Notes()
    exchange = tcp(trace=notes)
    started(exchange)
    assert exchange.receive(reply).registers == (555, 0, 100)
    assert notes.lines == [("received", reply, "")] and exchange.answered_id == 1
    assert exchange.framer.buffered == 0
    split = tcp()
    started(split)
    assert split.receive(reply[:5]) is None
    assert split.receive(reply[5:]).registers == (555, 0, 100)
    late = tcp()
    started(late)
    late.attempt(0x11, REQUEST, fresh=False)  # transaction 2: the reply to 1 comes first, then 2's
    second = TcpFramer().build(0x11, REPLY_PDU[:-1] + b"\x65", 2)
    assert late.receive(reply + second).registers == (555, 0, 101)


def test_tcp_after_a_retry_the_late_reply_to_the_first_attempt_answers():
    exchange = tcp()
    started(exchange)
    exchange.close()  # the first attempt timed out
    exchange.attempt(0x11, REQUEST, fresh=True, retry=True)
    assert exchange.attempt_ids == [1, 2]
    assert exchange.receive(TcpFramer().build(0x11, REPLY_PDU, 1)).registers == (555, 0, 100)
    assert exchange.answered_id == 1, "the client times the round trip from the first attempt"
    exchange.attempt(0x11, REQUEST, fresh=True)  # the next request: the old ids answer nothing
    assert exchange.attempt_ids == [3]


def test_tcp_our_transaction_id_with_a_wrong_byte_count_fails_at_once():
    exchange = tcp()
    started(exchange)
    with pytest.raises(MismatchError, match="byte count 2 does not fit 3 registers"):
        exchange.receive(TcpFramer().build(0x11, bytes.fromhex("03 02 00 01"), 1))


def test_tcp_a_copy_of_the_request_for_a_reply_says_the_server_echoes():
    exchange = tcp()
    adu = started(exchange)
    with pytest.raises(FrameError, match="the server, or a gateway on the way, echoes requests"):
        exchange.receive(adu)


@pytest.mark.parametrize("framer_type", [RtuFramer, AsciiFramer])
def test_an_echo_without_the_option_is_skipped_and_traced_as_one(framer_type):
    notes = Notes()
    exchange = Exchange(framer_type(), watch_echo=True, trace=notes)
    sent = started(exchange)
    assert exchange.receive(sent[:3]) is None
    assert exchange.receive(sent[3:]) is None
    assert exchange.receive(b"") is None
    reply = framer_type().build(0x11, REPLY_PDU)
    assert exchange.receive(reply).registers == (555, 0, 100)
    assert notes.lines[0] == ("received", sent, "the request's own echo, skipped (--echo strips it)")


def test_only_the_echo_is_an_invalid_response_and_says_so():
    exchange = serial()
    started(exchange)
    assert exchange.receive(SENT) is None
    assert exchange.close() is None
    assert "the only reply was a copy of the request" in str(exchange.problem)


def test_only_the_echo_then_a_hang_up_leaves_the_hang_up_to_tell():
    exchange = serial()
    started(exchange)
    exchange.receive(SENT)
    assert exchange.close(hung_up=True) is None and exchange.problem is None


def test_no_echo_is_watched_off_a_serial_line():
    exchange = Exchange(RtuFramer())  # a serial framing over TCP (an RTU-over-TCP gateway)
    started(exchange)
    assert exchange.receive(SENT) is None
    exchange.close()
    assert isinstance(exchange.problem, FrameError)
    assert "copy of the request" not in str(exchange.problem)


def test_with_echo_a_write_answered_by_its_copy_strips_only_the_first_copy():
    write = WriteSingleRegister(1, 3)
    exchange = serial(echo=True)
    sent = started(exchange, write)
    assert exchange.receive(sent) is None
    assert exchange.receive(sent) == write


def test_without_echo_a_write_answered_by_its_copy_is_answered():
    write = WriteSingleRegister(1, 3)
    exchange = serial()
    assert exchange.receive(started(exchange, write)) == write


def test_a_reply_that_starts_like_the_request_goes_on_as_soon_as_it_differs():
    request = ReadHoldingRegisters(0x0200, 1)  # request 11 03 02 00 ..., reply 11 03 02 ...
    exchange = serial()
    started(exchange, request)
    reply = rtu("11 03 02 00 07")
    assert exchange.receive(reply[:3]) is None
    assert exchange.receive(reply[3:]).registers == (7,)


def test_with_echo_bytes_that_are_not_the_echo_are_the_reply():
    exchange = serial(echo=True)
    started(exchange)
    assert exchange.receive(REPLY[:3]) is None
    assert exchange.receive(REPLY[3:]).registers == (555, 0, 100)


def test_lenient_takes_our_transaction_id_from_another_unit_and_notes_it():
    other_unit = TcpFramer().build(0x12, REPLY_PDU, 1)
    strict = tcp()
    started(strict)
    assert strict.receive(other_unit) is None
    strict.close()
    assert "(--lenient accepts a reply whose transaction id matches)" in str(strict.problem)
    notes = Notes()
    lenient = tcp(lenient=True, trace=notes)
    started(lenient)
    assert lenient.receive(other_unit).registers == (555, 0, 100)
    assert lenient.deviations == {"reply from unit 18, expected unit 17": None}
    assert notes.lines == [
        ("received", other_unit, "accepted (--lenient): reply from unit 18, expected unit 17")
    ]


def test_lenient_repairs_bytes_after_a_complete_reply_and_a_wrong_byte_count():
    trailing = TcpFramer().build(0x11, REPLY_PDU + b"\x00\x00", 1)
    miscounted = TcpFramer().build(0x11, bytes.fromhex("03 05 02 2B 00 00 00 64"), 1)
    for frame, deviation in (
        (trailing, "2 bytes after a complete reply, ignored"),
        (miscounted, "byte count 5, but the data is the 6 bytes asked for"),
    ):
        strict = tcp()
        started(strict)
        with pytest.raises(FrameError, match=f"{deviation}: --lenient accepts it"):
            strict.receive(frame)
        lenient = tcp(lenient=True)
        started(lenient)
        assert lenient.receive(frame).registers == (555, 0, 100)
        assert lenient.deviations == {deviation: None}


def test_the_same_reply_bytes_give_the_same_response_and_other_bytes_a_new_one():
    exchange = serial()
    started(exchange)
    first = exchange.receive(REPLY)
    started(exchange)
    assert exchange.receive(REPLY) is first
    started(exchange)
    changed = exchange.receive(rtu("11 03 06 02 2B 00 00 00 65"))
    assert changed is not first and changed.registers == (555, 0, 101)


def test_a_pause_ends_a_frame_whose_length_only_silence_tells():
    """RTU, a function code the codec does not know: only the pause the client waited ends it."""
    request = RawRequest(bytes.fromhex("41 01"))
    exchange = serial()
    started(exchange, request)
    reply = rtu("11 41 01 02 03")
    assert exchange.receive(reply) is None
    assert exchange.framer.waiting_for_silence
    assert exchange.receive(b"", ends_frame=True) is not None


def test_the_most_telling_problem():
    crc = ChecksumError("crc", b"x", 1, 2)
    garbage = FrameError("garbage")
    mismatch = MismatchError("unit")
    refusal = ModbusException(3, 2)
    assert worse(None, garbage) is garbage
    assert worse(garbage, crc) is crc
    assert worse(crc, garbage) is crc
    assert worse(mismatch, crc) is mismatch, "between equals, the first seen"
    assert worse(refusal, garbage) is garbage, "what came tells more than a busy device"
    silence = TimeoutError("silence")
    assert worse(silence, garbage) is garbage and worse(garbage, silence) is garbage


@pytest.mark.parametrize(
    "request_, pdu",
    [
        (ReadHoldingRegisters(0x6B, 3), REPLY_PDU),
        (ReadInputRegisters(0, 2), bytes.fromhex("04 04 FF FF 00 01")),
        (ReadCoils(0, 10), bytes.fromhex("01 02 CD 03")),  # bits past the tenth: trimmed, noted
    ],
)
def test_a_reply_as_predicted_decodes_as_the_parse_decodes_it(request_, pdu):
    """The predicted path decodes from where the PDU starts in the frame, without the checks
    the prediction made: the same response as decode_response's."""
    adu = TcpFramer().build(0x11, pdu, 1)
    assert request_.predicted_decoder(7)(adu) == request_.decode_response(pdu)


def test_tcp_a_reply_as_predicted_with_the_same_bytes_gives_the_same_response():
    """--same: a device read faster than its readings change answers with the same data under
    a new transaction id; the predicted path hands back the response decoded before."""
    exchange = tcp()
    framer = TcpFramer()
    started(exchange)
    first = exchange.receive(framer.build(0x11, REPLY_PDU, 1))
    started(exchange)
    assert exchange.receive(framer.build(0x11, REPLY_PDU, 2)) is first
    started(exchange)
    changed = exchange.receive(framer.build(0x11, REPLY_PDU[:-1] + b"\x65", 3))
    assert changed is not first and changed.registers == (555, 0, 101)


def test_requests_are_worked_out_once_each_and_a_stream_of_new_ones_is_not_kept_for_ever():
    """A map's requests take turns: each is framed and predicted once, then numbered only.
    Commands that send ever new requests (scan, dump) keep at most KNOWN_REQUESTS of them."""
    exchange = tcp()
    first, second = ReadHoldingRegisters(0, 2), ReadHoldingRegisters(10, 2)
    frames = [exchange.attempt(0x11, request, fresh=True) for request in (first, second, first, second)]
    assert [frame[2:] for frame in frames[:2]] == [frame[2:] for frame in frames[2:]]  # all but the ids
    assert [int.from_bytes(frame[:2], "big") for frame in frames] == [1, 2, 3, 4]
    reply = TcpFramer().build(0x11, bytes.fromhex("03 04 00 01 00 02"), 4)
    assert exchange.receive(reply).registers == (1, 2)  # the prediction is second's, at unit 0x11
    for address in range(KNOWN_REQUESTS + 10):
        exchange.attempt(0x11, ReadHoldingRegisters(address, 1), fresh=True)
    assert len(exchange._known) <= KNOWN_REQUESTS
