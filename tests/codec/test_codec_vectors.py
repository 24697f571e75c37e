"""Every worked example of the seeds (tests/data/vectors.json) through framers and PDU codec.

Each frame is fed three ways, after h11's tests: whole, one byte at a time, and
followed by trailing bytes; all three must yield the same Frame.
"""

from __future__ import annotations

import json

import pytest
from helpers.frames import drain_events, settle_events
from helpers.run import TESTS_DIR

from mbtool.codec import data_access, device_id, file_record, serial_line  # noqa: F401  (register every FC)
from mbtool.codec.ascii import AsciiFramer
from mbtool.codec.data_access import (
    BitsResponse,
    MaskWriteRegister,
    ReadCoils,
    ReadDiscreteInputs,
    ReadFifoQueue,
    ReadFifoQueueResponse,
    ReadHoldingRegisters,
    ReadInputRegisters,
    ReadWriteMultipleRegisters,
    RegistersResponse,
    WriteMultipleCoils,
    WriteMultipleRegisters,
    WriteMultipleResponse,
    WriteSingleCoil,
    WriteSingleRegister,
)
from mbtool.codec.errors import ChecksumError
from mbtool.codec.file_record import (
    FileRecord,
    FileRecordRequest,
    ReadFileRecord,
    ReadFileRecordResponse,
    WriteFileRecord,
)
from mbtool.codec.framer import Frame, Rejected
from mbtool.codec.mbap import TcpFramer
from mbtool.codec.pdu import ExceptionResponse, Response, decode_request, decode_response
from mbtool.codec.rtu import RtuFramer
from mbtool.codec.serial_line import (
    CommEventCounterResponse,
    CommEventLogResponse,
    Diagnostics,
    DiagnosticSubFunction,
    ExceptionStatusResponse,
    GetCommEventCounter,
    GetCommEventLog,
    ReadExceptionStatus,
    ReportSlaveId,
)

VECTORS = json.loads((TESTS_DIR / "data" / "vectors.json").read_text())
SERIAL = {v["name"]: v for v in VECTORS["serial"]}

# Requests whose reply is an echo: the same bytes also make a valid reply.
ECHOES = {"fc05-request", "fc06-request", "fc08-request", "fc21-request", "fc22-request"}

# request vector -> its reply vector
PAIRS = {name: name.replace("-request", "-response") for name in SERIAL if name.endswith("-request")}
PAIRS["fig7-request"] = "fig8-response"
PAIRS = {req: resp for req, resp in PAIRS.items() if resp in SERIAL}

# What each vector means, as the seeds and the spec describe it.
MEANING = {
    "fc01-request": ReadCoils(19, 37),
    "fc02-request": ReadDiscreteInputs(0xC4, 22),
    "fc02-response": BitsResponse(2, tuple(bool(b >> i & 1) for b in (0xAC, 0xDB, 0x35) for i in range(8))),
    "fc03-request": ReadHoldingRegisters(107, 3),
    "fc03-response": RegistersResponse(3, (555, 0, 100)),
    "fc04-request": ReadInputRegisters(8, 1),
    "fc04-response": RegistersResponse(4, (10,)),
    "fc05-request": WriteSingleCoil(172, True),
    "fc06-request": WriteSingleRegister(1, 3),
    "fc07-request": ReadExceptionStatus(),
    "fc07-response": ExceptionStatusResponse(0x6D),
    "fc08-request": Diagnostics(DiagnosticSubFunction.RETURN_QUERY_DATA, b"\xa5\x37"),
    "fc11-request": GetCommEventCounter(),
    "fc11-response": CommEventCounterResponse(0xFFFF, 264),
    "fc12-request": GetCommEventLog(),
    "fc12-response": CommEventLogResponse(0, 264, 289, b"\x20\x00"),
    "fc15-request": WriteMultipleCoils(19, (True, False, True, True, False, False, True, True, True, False)),
    "fc15-response": WriteMultipleResponse(0x0F, 19, 10),
    "fc16-request": WriteMultipleRegisters(1, (0x000A, 0x0102)),
    "fc16-response": WriteMultipleResponse(0x10, 1, 2),
    "fc17-request": ReportSlaveId(),
    "fc20-request": ReadFileRecord((FileRecordRequest(4, 1, 2), FileRecordRequest(3, 9, 2))),
    "fc20-response": ReadFileRecordResponse(((0x0DFE, 0x0020), (0x33CD, 0x0040))),
    "fc21-request": WriteFileRecord((FileRecord(4, 7, (0x06AF, 0x04BE, 0x100D)),)),
    "fc22-request": MaskWriteRegister(4, 0x00F2, 0x0025),
    "fc23-request": ReadWriteMultipleRegisters(4, 6, 15, (0xFF, 0xFF, 0xFF)),
    "fc23-response": RegistersResponse(0x17, (0x00FE, 0x0ACD, 0x0001, 0x0003, 0x000D, 0x00FF)),
    "fc24-request": ReadFifoQueue(0x04DE),
    "fc24-response": ReadFifoQueueResponse((0x01B8, 0x1284, 0x1322)),
    "exception-request": ReadCoils(0x04A1, 1),
    "exception-response": ExceptionResponse(0x01, 0x02),
    "seed003-fc16-request": WriteMultipleRegisters(0x10, (100, 10000)),
}

TRAILING = b"\x00\xff\x13\x37"


def _cases():
    """(vector, reads replies?) for every serial vector, and echo requests read as replies too."""
    cases = []
    for name, vector in SERIAL.items():
        responses = name.endswith("-response")
        cases.append(pytest.param(vector, responses, id=name))
        if name in ECHOES:
            cases.append(pytest.param(vector, True, id=f"{name}-as-echo"))
    return cases


CASES = _cases()


def _rtu(vector) -> bytes:
    return bytes.fromhex(vector["rtu_frame"])


def _ascii(vector) -> bytes:
    return vector["ascii_frame"].encode()


def _pdu(vector) -> bytes:
    return bytes.fromhex(vector["unit_and_pdu"])[1:]


def _unit(vector) -> int:
    return bytes.fromhex(vector["unit_and_pdu"])[0]


def feed(framer, data: bytes, how: str) -> list:
    if how == "whole":
        framer.feed(data)
        return drain_events(framer)
    if how == "bytewise":
        events = []
        for i in range(len(data)):
            framer.feed(data[i : i + 1])
            events += drain_events(framer)
        return events
    assert how == "trailing"
    framer.feed(data + TRAILING)
    return settle_events(framer)


HOW = ["whole", "bytewise", "trailing"]


@pytest.mark.parametrize("how", HOW)
@pytest.mark.parametrize(("vector", "responses"), CASES)
def test_rtu_frame(vector, responses, how):
    frame = _rtu(vector)
    events = feed(RtuFramer(responses=responses), frame, how)
    assert events[0] == Frame(_unit(vector), _pdu(vector), frame)
    if how == "trailing":
        assert all(isinstance(event, Rejected) for event in events[1:])
        assert b"".join(event.data for event in events[1:]) == TRAILING
    else:
        assert len(events) == 1


@pytest.mark.parametrize("how", HOW)
@pytest.mark.parametrize(("vector", "responses"), CASES)
def test_ascii_frame(vector, responses, how):
    frame = _ascii(vector)
    events = feed(AsciiFramer(responses=responses), frame, how)
    assert events[0] == Frame(_unit(vector), _pdu(vector), frame)
    if how == "trailing":
        assert all(isinstance(event, Rejected) for event in events[1:])
    else:
        assert len(events) == 1


@pytest.mark.parametrize(("vector", "responses"), CASES)
def test_pdu_decodes_and_reencodes(vector, responses):
    pdu = _pdu(vector)
    decoded = decode_response(pdu) if responses else decode_request(pdu)
    assert decoded.encode() == pdu
    as_echo = responses and not vector["name"].endswith("-response")
    if vector["name"] in MEANING and not as_echo:
        assert decoded == MEANING[vector["name"]]
    if isinstance(decoded, Response):
        assert decoded.warnings == ()


@pytest.mark.parametrize("vector", list(SERIAL.values()), ids=list(SERIAL))
def test_framers_build_the_frame(vector):
    unit, pdu = _unit(vector), _pdu(vector)
    assert RtuFramer().build(unit, pdu) == _rtu(vector)
    assert AsciiFramer().build(unit, pdu) == _ascii(vector)


@pytest.mark.parametrize(("request_name", "reply_name"), PAIRS.items(), ids=list(PAIRS))
def test_reply_answers_its_request(request_name, reply_name):
    request = decode_request(_pdu(SERIAL[request_name]))
    reply_pdu = _pdu(SERIAL[reply_name])
    reply = request.decode_response(reply_pdu)
    assert type(reply) is type(decode_response(reply_pdu))
    assert reply.encode() == reply_pdu
    # A framer that knows the request ends the reply by the request's own rule.
    framer = RtuFramer(responses=True)
    framer.expect = request
    framer.feed(_rtu(SERIAL[reply_name]))
    assert drain_events(framer) == [Frame(_unit(SERIAL[reply_name]), reply_pdu, _rtu(SERIAL[reply_name]))]


@pytest.mark.parametrize("name", sorted(ECHOES))
def test_echo_answers_its_request(name):
    request = decode_request(_pdu(SERIAL[name]))
    assert request.decode_response(_pdu(SERIAL[name])) == request or isinstance(request, Diagnostics)
    assert request.decode_response(_pdu(SERIAL[name])).encode() == request.encode()


def test_meanings_of_the_worked_examples():
    counter = decode_response(_pdu(SERIAL["fc11-response"]))
    assert counter.busy and counter.event_count == 264
    log = decode_response(_pdu(SERIAL["fc12-response"]))
    assert log.descriptions == ("unrecognised event 0x20", "communications restart")
    mask = decode_request(_pdu(SERIAL["fc22-request"]))
    assert mask.result(0x12) == 0x17
    coils = ReadCoils(19, 37).decode_response(_pdu(SERIAL["fc01-response"]))
    assert len(coils.bits) == 37 and coils.warnings == ()
    # seed 002 fig. 11: coils 27..20 are CD = 1100 1101, coil 20 first.
    assert coils.bits[:8] == (True, False, True, True, False, False, True, True)


# --- Modbus TCP ---------------------------------------------------------------------------

TCP = VECTORS["tcp"]


@pytest.mark.parametrize("how", HOW)
@pytest.mark.parametrize("vector", TCP, ids=[v["name"] for v in TCP])
def test_tcp_frame(vector, how):
    adu = bytes.fromhex(vector["adu"])
    responses = "request" not in vector["name"]
    events = feed(TcpFramer(responses=responses), adu, how)
    assert events[0] == Frame(9, adu[7:], adu, 0)
    if how != "trailing":
        assert len(events) == 1
    assert TcpFramer().build(9, adu[7:], 0) == adu
    decoded = decode_response(adu[7:]) if responses else decode_request(adu[7:])
    assert decoded.encode() == adu[7:]


def test_tcp_example_means_what_seed001_says():
    request = decode_request(bytes.fromhex(TCP[0]["adu"])[7:])
    assert request == ReadHoldingRegisters(4, 1)
    assert request.decode_response(bytes.fromhex(TCP[1]["adu"])[7:]) == RegistersResponse(3, (5,))
    assert decode_response(bytes.fromhex(TCP[2]["adu"])[7:]) == RegistersResponse(3, (0x1234,))


def test_tcp_transaction_id_is_kept():
    framer = TcpFramer()
    framer.feed(framer.build(9, bytes.fromhex("03 02 00 05"), 0xBEEF))
    event = framer.next_event()
    assert event.transaction_id == 0xBEEF and event.unit == 9


# --- frames with a wrong checksum ------------------------------------------------------------

BAD = VECTORS["bad_crc"]


def _bad_cases():
    for vector in BAD:
        # FC06's request and reply look alike: read it both ways.
        directions = [False, True] if "fc06" in vector["name"] else ["response" in vector["name"]]
        for responses in directions:
            yield pytest.param(
                vector, responses, id=f"{vector['name']}-{'reply' if responses else 'request'}"
            )


@pytest.mark.parametrize(("vector", "responses"), list(_bad_cases()))
def test_bad_crc_is_rejected_with_the_expected_crc(vector, responses):
    frame = bytes.fromhex(vector["frame"])
    framer = RtuFramer(responses=responses)
    framer.feed(frame)
    events = settle_events(framer)
    assert events and all(isinstance(event, Rejected) for event in events)
    error = events[0].error
    assert isinstance(error, ChecksumError)
    # CRC goes low byte first: the expected bytes as printed read little-endian.
    assert error.expected == int.from_bytes(bytes.fromhex(vector["expected_crc"]), "little")
    assert error.received == int.from_bytes(frame[-2:], "little")
    assert error.data == frame
    assert b"".join(event.data for event in events) == frame


def test_bad_lrc_is_rejected_with_the_expected_lrc():
    good = _ascii(SERIAL["exception-request"])  # :0A0104A100014F
    framer = AsciiFramer(responses=False)
    framer.feed(good.replace(b"4F\r", b"4E\r"))
    event = framer.next_event()
    assert isinstance(event, Rejected)
    assert isinstance(event.error, ChecksumError)
    assert (event.error.expected, event.error.received) == (0x4F, 0x4E)


# --- seed 003: a reply with nonzero padding bits ------------------------------------------------


def test_nonzero_padding_bits_carry_a_warning():
    reply = ReadCoils(0x13, 10).decode_response(bytes.fromhex("0102CD6B"))
    assert isinstance(reply, BitsResponse)
    assert len(reply.bits) == 10
    assert reply.warnings


def test_zero_padding_bits_carry_no_warning():
    reply = ReadCoils(0x13, 10).decode_response(bytes.fromhex("0102CD01"))
    assert reply.bits == (True, False, True, True, False, False, True, True, True, False)
    assert reply.warnings == ()
