"""Hypothesis: round trips for every function code; arbitrary bytes never crash a decoder or framer.

A request and a reply that answers it are drawn together, so the reply can be
checked against the request and framed by the request's own length rule.
"""

from __future__ import annotations

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mbtool.codec import data_access as da
from mbtool.codec import device_id as di
from mbtool.codec import file_record as fr
from mbtool.codec import serial_line as sl
from mbtool.codec.ascii import AsciiFramer
from mbtool.codec.errors import ProtocolError
from mbtool.codec.framer import Frame, Rejected
from mbtool.codec.mbap import TcpFramer
from mbtool.codec.pdu import (
    FUNCTIONS,
    MAX_PDU,
    ExceptionResponse,
    Request,
    decode_request,
    decode_response,
    unpack_bits,
    unpack_registers,
)
from mbtool.codec.rtu import RtuFramer

SETTINGS = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])

u8 = st.integers(0, 0xFF)
u16 = st.integers(0, 0xFFFF)


def span(limit: int):
    """(address, count) with 1 <= count <= limit and the span inside the 65536-item table."""
    return st.integers(1, limit).flatmap(lambda n: st.tuples(st.integers(0, 0x10000 - n), st.just(n)))


def registers(n: int):
    # Drawn as bytes: hypothesis draws a 250-byte string far faster than 125 integers.
    return st.binary(min_size=2 * n, max_size=2 * n).map(unpack_registers)


def bits(n: int):
    size = (n + 7) // 8
    return st.binary(min_size=size, max_size=size).map(lambda data: unpack_bits(data, n))


# --- a request and a reply that answers it, per function code ----------------------------------


def _bits(kind):
    def pair(address_count):
        address, count = address_count
        request = kind(address, count)
        return bits(count).map(lambda b: (request, da.BitsResponse(kind.function_code, b)))

    return span(da.MAX_READ_BITS).flatmap(pair)


def _registers(kind):
    def pair(address_count):
        request = kind(*address_count)
        return registers(request.count).map(lambda r: (request, da.RegistersResponse(kind.function_code, r)))

    return span(da.MAX_READ_REGISTERS).flatmap(pair)


def _echo(requests):
    return requests.map(lambda request: (request, request))


def _write_multiple(kind, values, limit):
    def make(address_count):
        address, count = address_count
        return values(count).map(lambda v: kind(address, v))

    requests = span(limit).flatmap(make)
    return requests.map(lambda r: (r, da.WriteMultipleResponse(kind.function_code, r.address, len(r.values))))


def _read_write():
    def make(parts):
        (read_address, read_count), (write_address, write_count) = parts
        request = st.builds(
            da.ReadWriteMultipleRegisters,
            st.just(read_address),
            st.just(read_count),
            st.just(write_address),
            registers(write_count),
        )
        return st.tuples(request, registers(read_count).map(lambda r: da.RegistersResponse(0x17, r)))

    return st.tuples(span(da.MAX_READ_REGISTERS), span(da.MAX_READ_WRITE_REGISTERS)).flatmap(make)


def _fifo():
    fifo = st.integers(0, da.MAX_FIFO_COUNT).flatmap(registers)
    return st.tuples(st.builds(da.ReadFifoQueue, u16), st.builds(da.ReadFifoQueueResponse, fifo))


_KNOWN_SUBS = [sub for sub in sl.DiagnosticSubFunction if sub != sl.DiagnosticSubFunction.RETURN_QUERY_DATA]
_UNKNOWN_SUBS = st.integers(0, 0xFFFF).filter(lambda s: s not in {int(x) for x in sl.DiagnosticSubFunction})


def _diagnostics():
    def reply(request):
        sub = request.sub_function
        if sub in sl.ECHO_SUB_FUNCTIONS or (
            sub == sl.Sub.MODBUS_PLUS_STATS and request.data != sl.MODBUS_PLUS_GET
        ):
            return st.just(sl.DiagnosticsResponse(sub, request.data))
        if sub == sl.Sub.MODBUS_PLUS_STATS:
            words = st.lists(u16, max_size=sl.MODBUS_PLUS_WORDS).map(
                lambda w: b"".join(x.to_bytes(2, "big") for x in w)
            )
            return words.map(lambda w: sl.DiagnosticsResponse(sub, sl.MODBUS_PLUS_GET + bytes([len(w)]) + w))
        return st.binary(min_size=2, max_size=2).map(lambda d: sl.DiagnosticsResponse(sub, d))

    requests = st.one_of(
        st.builds(sl.Diagnostics, st.just(sl.Sub.RETURN_QUERY_DATA), st.binary(max_size=MAX_PDU - 3)),
        st.builds(sl.Diagnostics, st.sampled_from(_KNOWN_SUBS), st.binary(min_size=2, max_size=2)),
        st.builds(
            sl.Diagnostics,
            st.just(sl.Sub.MODBUS_PLUS_STATS),
            st.sampled_from([sl.MODBUS_PLUS_GET, sl.MODBUS_PLUS_CLEAR]),
        ),
        st.builds(sl.Diagnostics, _UNKNOWN_SUBS, st.binary(min_size=2, max_size=2)),
    )
    return requests.flatmap(lambda r: reply(r).map(lambda resp: (r, resp)))


def _slave_id():
    proper = st.builds(sl.ReportSlaveIdResponse, u8, st.booleans(), st.binary(max_size=MAX_PDU - 4))
    odd_run = st.builds(
        lambda slave, raw, extra: sl.ReportSlaveIdResponse(slave, True, extra, run_indicator_byte=raw),
        u8,
        st.integers(0x01, 0xFE),
        st.binary(max_size=20),
    )
    return st.tuples(st.just(sl.ReportSlaveId()), st.one_of(proper, odd_run))


def _file_read():
    def group(_):
        return st.integers(1, 5).flatmap(
            lambda n: st.builds(
                fr.FileRecordRequest,
                st.integers(1, 0xFFFF),
                st.integers(0, fr.MAX_RECORD + 1 - n),
                st.just(n),
            )
        )

    groups = st.lists(group(None), min_size=1, max_size=20).map(tuple)

    def pair(gs):
        records = st.tuples(*(registers(g.length) for g in gs))
        return records.map(lambda r: (fr.ReadFileRecord(gs), fr.ReadFileRecordResponse(r)))

    return groups.flatmap(pair)


def _file_write():
    record = st.lists(u16, min_size=1, max_size=20).flatmap(
        lambda v: st.builds(
            fr.FileRecord,
            st.integers(1, 0xFFFF),
            st.integers(0, fr.MAX_RECORD + 1 - len(v)),
            st.just(tuple(v)),
        )
    )
    return _echo(st.lists(record, min_size=1, max_size=5).map(lambda g: fr.WriteFileRecord(tuple(g))))


def _device_id():
    def pair(request):
        obj = st.tuples(u8, st.binary(max_size=40))
        if request.read_code == di.ReadDeviceIdCode.SPECIFIC:
            objects = st.binary(max_size=200).map(lambda v: ((request.object_id, v),))
        else:
            objects = st.lists(obj, max_size=5).map(tuple)
        reply = st.builds(
            di.DeviceIdentificationResponse,
            st.just(int(request.read_code)),
            st.sampled_from(sorted(di.CONFORMITY_LEVELS)),
            st.booleans(),
            u8,
            objects,
        )
        return reply.map(lambda r: (request, r))

    return st.builds(di.ReadDeviceIdentification, st.integers(1, 4), u8).flatmap(pair)


PAIRS = {
    0x01: _bits(da.ReadCoils),
    0x02: _bits(da.ReadDiscreteInputs),
    0x03: _registers(da.ReadHoldingRegisters),
    0x04: _registers(da.ReadInputRegisters),
    0x05: _echo(st.builds(da.WriteSingleCoil, u16, st.booleans())),
    0x06: _echo(st.builds(da.WriteSingleRegister, u16, u16)),
    0x07: st.tuples(st.just(sl.ReadExceptionStatus()), st.builds(sl.ExceptionStatusResponse, u8)),
    0x08: _diagnostics(),
    0x0B: st.tuples(st.just(sl.GetCommEventCounter()), st.builds(sl.CommEventCounterResponse, u16, u16)),
    0x0C: st.tuples(
        st.just(sl.GetCommEventLog()),
        st.builds(sl.CommEventLogResponse, u16, u16, u16, st.binary(max_size=sl.MAX_EVENTS)),
    ),
    0x0F: _write_multiple(da.WriteMultipleCoils, bits, da.MAX_WRITE_COILS),
    0x10: _write_multiple(da.WriteMultipleRegisters, registers, da.MAX_WRITE_REGISTERS),
    0x11: _slave_id(),
    0x14: _file_read(),
    0x15: _file_write(),
    0x16: _echo(st.builds(da.MaskWriteRegister, u16, u16, u16)),
    0x17: _read_write(),
    0x18: _fifo(),
    0x2B: _device_id(),
}


def test_every_function_code_has_a_strategy():
    assert sorted(PAIRS) == sorted(FUNCTIONS)


CODES = sorted(PAIRS)


def _fits_class_size(request: Request) -> bool:
    """Without the request, a return-query-data reply is assumed 2 data bytes long (documented)."""
    return not (isinstance(request, sl.Diagnostics) and request.sub_function == 0 and len(request.data) != 2)


@pytest.mark.parametrize("code", CODES, ids=[f"fc{c:02d}" for c in CODES])
def test_round_trips(code):
    @SETTINGS
    @given(PAIRS[code], st.integers(1, 247))
    def check(pair, unit):
        request, reply = pair
        assert request.function_code == code
        pdu = request.encode()
        assert len(pdu) <= MAX_PDU
        assert decode_request(pdu) == request
        assert type(request).decode(pdu) == request

        reply_pdu = reply.encode()
        assert len(reply_pdu) <= MAX_PDU
        answered = request.decode_response(reply_pdu)
        assert answered == reply
        assert answered.encode() == reply_pdu
        offline = decode_response(reply_pdu)
        assert offline.encode() == reply_pdu  # bits replies keep their padding when no request trims them

        # Implicit length: the reply framed by the request's rule, the request by the class rule.
        assert request.response_length(reply_pdu) == len(reply_pdu)
        for framer_type in (RtuFramer, AsciiFramer, TcpFramer):
            client = framer_type(responses=True)
            client.expect = request
            client.feed(client.build(unit, reply_pdu, 7))
            event = client.next_event()
            assert isinstance(event, Frame) and event.pdu == reply_pdu and event.unit == unit
            if _fits_class_size(request):
                server = framer_type(responses=False)
                server.feed(server.build(unit, pdu, 7))
                event = server.next_event()
                assert isinstance(event, Frame) and event.pdu == pdu

        # The device's "no" is always understood.
        no = ExceptionResponse(code, 0x02).encode()
        assert request.decode_response(no) == ExceptionResponse(code, 0x02)

    check()


# --- arbitrary bytes --------------------------------------------------------------------------

REQUEST_TYPES = [FUNCTIONS[c] for c in CODES]
RESPONSE_TYPES = sorted(
    {kind.response_type for kind in REQUEST_TYPES} | {sl.DiagnosticsResponse}, key=lambda t: t.__name__
)

SAMPLE_REQUESTS = [
    da.ReadCoils(0, 10),
    da.ReadDiscreteInputs(0, 2000),
    da.ReadHoldingRegisters(0, 3),
    da.ReadInputRegisters(0, 125),
    da.WriteSingleCoil(1, True),
    da.WriteSingleRegister(1, 2),
    sl.ReadExceptionStatus(),
    sl.Diagnostics(0, b"\x12\x34\x56"),
    sl.Diagnostics(sl.Sub.MODBUS_PLUS_STATS, sl.MODBUS_PLUS_GET),
    sl.Diagnostics(sl.Sub.BUS_MESSAGE_COUNT),
    sl.GetCommEventCounter(),
    sl.GetCommEventLog(),
    da.WriteMultipleCoils(0, (True,) * 10),
    da.WriteMultipleRegisters(0, (1, 2)),
    sl.ReportSlaveId(),
    fr.ReadFileRecord((fr.FileRecordRequest(1, 0, 2),)),
    fr.WriteFileRecord((fr.FileRecord(1, 0, (1, 2)),)),
    da.MaskWriteRegister(0, 0xF2, 0x25),
    da.ReadWriteMultipleRegisters(0, 2, 0, (1,)),
    da.ReadFifoQueue(0),
    di.ReadDeviceIdentification(1, 0),
    di.ReadDeviceIdentification(4, 5),
]

# Mostly a known function code in front, so each decoder is reached past its first check.
pdus = st.one_of(
    st.binary(max_size=MAX_PDU + 4),
    st.tuples(st.sampled_from(CODES + [c | 0x80 for c in CODES]), st.binary(max_size=MAX_PDU)).map(
        lambda t: bytes([t[0]]) + t[1]
    ),
)


def _only_our_errors(call, *args):
    try:
        return call(*args)
    except ProtocolError:
        return None


@settings(max_examples=300, deadline=None)
@given(pdus)
def test_arbitrary_pdus_raise_only_our_errors(pdu):
    _only_our_errors(decode_request, pdu)
    _only_our_errors(decode_response, pdu)
    for request in SAMPLE_REQUESTS:
        _only_our_errors(request.decode_response, pdu)
        length = request.response_length(pdu)
        assert length is None or isinstance(length, int)
    for kind in REQUEST_TYPES:
        _only_our_errors(kind.decode, pdu)
        for size in (kind.request_size, kind.response_size):
            length = size.of(pdu)
            assert length is None or isinstance(length, int)
    for kind in RESPONSE_TYPES:
        _only_our_errors(kind.decode, pdu)


@settings(max_examples=200, deadline=None)
@given(pdus)
def test_whatever_decodes_survives_a_second_trip(pdu):
    """decode(encode(decode(x))) == decode(x).

    Not decode(x).encode() == x: padding bits of a coil write, or a more-follows byte
    that is neither 00 nor FF, are read leniently and written the proper way.
    """
    for decode in (decode_request, decode_response):
        decoded = _only_our_errors(decode, pdu)
        if decoded is not None:
            again = decode(decoded.encode())
            assert again == decoded
            assert again.encode() == decoded.encode()


FRAMERS = [RtuFramer, AsciiFramer, TcpFramer]
chunks = st.lists(
    st.one_of(
        st.binary(max_size=40),
        # pieces of real frames make the framers work harder than noise alone
        st.builds(
            lambda framer, unit, request: framer().build(unit, request.encode(), 1),
            st.sampled_from(FRAMERS),
            u8,
            st.sampled_from(SAMPLE_REQUESTS),
        ),
        st.just(b":"),
        st.just(b"\r\n"),
    ),
    max_size=12,
)


@pytest.mark.parametrize("responses", [True, False], ids=["replies", "requests"])
@pytest.mark.parametrize("framer_type", FRAMERS, ids=lambda f: f.name)
def test_arbitrary_bytes_into_framers_give_only_events(framer_type, responses):
    @settings(max_examples=60, deadline=None)
    @given(chunks, st.sampled_from([None, *SAMPLE_REQUESTS]))
    def check(pieces, expect):
        framer = framer_type(responses=responses)
        framer.expect = expect
        fed = b"".join(pieces)
        out = 0
        for piece in pieces:
            framer.feed(piece)
            while (event := framer.next_event()) is not None:
                assert isinstance(event, Frame | Rejected)
                if isinstance(event, Rejected):
                    assert isinstance(event.error, ProtocolError) and event.data
                out += len(event.adu if isinstance(event, Frame) else event.data)
            assert isinstance(framer.waiting_for_silence, bool)
        for _ in range(len(fed) + 2):
            event = framer.silence()
            if event is None:
                break
            assert isinstance(event, Frame | Rejected)
            out += len(event.adu if isinstance(event, Frame) else event.data)
        assert framer.silence() is None
        assert framer.buffered == 0
        assert out == len(fed)  # every byte comes out once, as a frame or as rejected bytes

    check()
