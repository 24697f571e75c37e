"""Every limit of the spec (§3-§6), and the exception code a server would answer to breaking it.

RequestError.exception_code: 02 Illegal Data Address for addresses, 03 Illegal
Data Value for quantities and values.
"""

from __future__ import annotations

import struct

import pytest

from mbtool.codec import data_access as da
from mbtool.codec import device_id as di
from mbtool.codec import file_record as fr
from mbtool.codec import serial_line as sl
from mbtool.codec.errors import DecodeError, MismatchError, RequestError
from mbtool.codec.pdu import MAX_PDU, ExceptionCode, decode_request, decode_response

ADDRESS = ExceptionCode.ILLEGAL_DATA_ADDRESS
VALUE = ExceptionCode.ILLEGAL_DATA_VALUE


def refused(code: int, make, *args, **kwargs) -> RequestError:
    with pytest.raises(RequestError) as caught:
        make(*args, **kwargs)
    assert caught.value.exception_code == code, str(caught.value)
    return caught.value


# --- quantities: 0 and limit + 1 refused, the limit itself accepted -----------------------------

QUANTITY_LIMITS = [
    (da.ReadCoils, 2000),
    (da.ReadDiscreteInputs, 2000),
    (da.ReadHoldingRegisters, 125),
    (da.ReadInputRegisters, 125),
]


@pytest.mark.parametrize(("kind", "limit"), QUANTITY_LIMITS, ids=lambda x: getattr(x, "__name__", str(x)))
def test_read_quantities(kind, limit):
    assert kind(0, limit).count == limit
    refused(VALUE, kind, 0, 0)
    refused(VALUE, kind, 0, limit + 1)


@pytest.mark.parametrize(("kind", "limit"), QUANTITY_LIMITS, ids=lambda x: getattr(x, "__name__", str(x)))
def test_read_quantities_on_the_server_side(kind, limit):
    # A device decoding such a request answers exception 03.
    for count in (0, limit + 1):
        refused(VALUE, kind.decode, struct.pack(">BHH", kind.function_code, 0, count))


def test_write_multiple_coils_quantity():
    assert len(da.WriteMultipleCoils(0, (True,) * 1968).values) == 1968
    refused(VALUE, da.WriteMultipleCoils, 0, ())
    refused(VALUE, da.WriteMultipleCoils, 0, (True,) * 1969)


def test_write_multiple_registers_quantity():
    # seed 000's 0x78 is wrong: the spec allows 123 (0x7B).
    assert len(da.WriteMultipleRegisters(0, (0,) * 123).values) == 123
    refused(VALUE, da.WriteMultipleRegisters, 0, ())
    refused(VALUE, da.WriteMultipleRegisters, 0, (0,) * 124)


def test_write_multiple_quantity_on_the_server_side():
    refused(VALUE, da.WriteMultipleRegisters.decode, bytes.fromhex("10 0000 007C F8") + bytes(0xF8))
    refused(VALUE, da.WriteMultipleCoils.decode, bytes.fromhex("0F 0000 0000 00"))
    # byte count that does not fit the quantity
    refused(VALUE, da.WriteMultipleRegisters.decode, bytes.fromhex("10 0000 0002 02 0001"))
    refused(VALUE, da.WriteMultipleCoils.decode, bytes.fromhex("0F 0000 000A 01 FF"))


def test_read_write_multiple_quantities():
    assert da.ReadWriteMultipleRegisters(0, 125, 0, (0,) * 121)
    refused(VALUE, da.ReadWriteMultipleRegisters, 0, 0, 0, (1,))
    refused(VALUE, da.ReadWriteMultipleRegisters, 0, 126, 0, (1,))
    refused(VALUE, da.ReadWriteMultipleRegisters, 0, 1, 0, ())
    refused(VALUE, da.ReadWriteMultipleRegisters, 0, 1, 0, (0,) * 122)


def test_read_write_multiple_on_the_server_side():
    good = da.ReadWriteMultipleRegisters(4, 6, 15, (0xFF,) * 3).encode()
    assert da.ReadWriteMultipleRegisters.decode(good).values == (0xFF,) * 3
    bad_count = good[:7] + b"\x00\x02" + good[9:]  # write quantity 2, byte count still 6
    refused(VALUE, da.ReadWriteMultipleRegisters.decode, bad_count)
    refused(VALUE, da.ReadWriteMultipleRegisters.decode, good[:3] + b"\x00\x7e" + good[5:])  # read 126


def test_read_write_reply_must_fit_the_read_quantity():
    request = da.ReadWriteMultipleRegisters(4, 2, 15, (1,))
    assert request.decode_response(bytes.fromhex("17 04 0001 0002")).registers == (1, 2)
    with pytest.raises(MismatchError):
        request.decode_response(bytes.fromhex("17 02 0001"))


# --- addresses: span past 65536, exception 02 ---------------------------------------------------


@pytest.mark.parametrize(
    ("make", "args"),
    [
        (da.ReadCoils, (65535, 2)),
        (da.ReadDiscreteInputs, (64000, 2000)),
        (da.ReadHoldingRegisters, (65500, 37)),
        (da.ReadInputRegisters, (65535, 2)),
        (da.WriteMultipleCoils, (65535, (True, True))),
        (da.WriteMultipleRegisters, (65535, (1, 2))),
        (da.ReadWriteMultipleRegisters, (65535, 2, 0, (1,))),
        (da.ReadWriteMultipleRegisters, (0, 1, 65535, (1, 2))),
    ],
    ids=lambda x: getattr(x, "__name__", None),
)
def test_span_past_the_table_is_an_address_error(make, args):
    refused(ADDRESS, make, *args)


def test_span_up_to_the_last_item_is_fine():
    assert da.ReadCoils(65535, 1).address == 65535
    assert da.ReadHoldingRegisters(65536 - 125, 125).count == 125
    assert da.WriteMultipleRegisters(65534, (1, 2)).address == 65534


def test_span_on_the_server_side():
    refused(ADDRESS, da.ReadHoldingRegisters.decode, bytes.fromhex("03 FFFF 0002"))


@pytest.mark.parametrize(
    "make",
    [
        lambda: da.ReadCoils(-1, 1),
        lambda: da.ReadHoldingRegisters(65536, 1),
        lambda: da.WriteSingleCoil(65536, True),
        lambda: da.WriteSingleRegister(-1, 0),
        lambda: da.MaskWriteRegister(65536, 0, 0),
        lambda: da.ReadFifoQueue(65536),
    ],
)
def test_address_out_of_range_is_an_address_error(make):
    refused(ADDRESS, make)


@pytest.mark.parametrize(
    "make",
    [
        lambda: da.WriteSingleRegister(0, 65536),
        lambda: da.WriteSingleRegister(0, -1),
        lambda: da.WriteMultipleRegisters(0, (1, 70000)),
        lambda: da.MaskWriteRegister(0, 0x10000, 0),
        lambda: da.MaskWriteRegister(0, 0, -1),
        lambda: da.ReadWriteMultipleRegisters(0, 1, 0, (0x10000,)),
    ],
)
def test_register_value_out_of_range_is_a_value_error(make):
    refused(VALUE, make)


# --- FC05: FF00 or 0000, nothing else -------------------------------------------------------------


@pytest.mark.parametrize("value", [0x0001, 0x00FF, 0xFF01, 0xFFFF, 0x1234])
def test_write_single_coil_value_other_than_ff00_or_0000(value):
    pdu = struct.pack(">BHH", 0x05, 172, value)
    refused(VALUE, da.WriteSingleCoil.decode, pdu)
    refused(VALUE, decode_request, pdu)


def test_write_single_coil_values():
    assert da.WriteSingleCoil.decode(bytes.fromhex("05 00AC FF00")).on is True
    assert da.WriteSingleCoil.decode(bytes.fromhex("05 00AC 0000")).on is False


def test_a_bad_coil_echo_is_a_bad_reply_not_bad_usage():
    # Something was sent: the fault is the device's, exit code "invalid response", not "usage".
    with pytest.raises(DecodeError):
        da.WriteSingleCoil(172, True).decode_response(bytes.fromhex("05 00AC 1234"))
    with pytest.raises(DecodeError):
        decode_response(bytes.fromhex("05 00AC 1234"))


def test_echo_must_echo():
    with pytest.raises(MismatchError):
        da.WriteSingleCoil(172, True).decode_response(bytes.fromhex("05 00AC 0000"))
    with pytest.raises(MismatchError):
        da.MaskWriteRegister(4, 0xF2, 0x25).decode_response(bytes.fromhex("16 0004 00F2 0026"))


# --- FC22: the mask write formula ------------------------------------------------------------------


def test_mask_write_result_of_the_spec_example():
    # Spec §3: current 0x12, AND 0xF2, OR 0x25 -> 0x17 (seed 002's formula would give 0x32).
    assert da.mask_write_result(0x12, 0xF2, 0x25) == 0x17
    assert da.MaskWriteRegister(4, 0xF2, 0x25).result(0x12) == 0x17


def test_mask_write_result_edge_cases():
    assert da.mask_write_result(0xABCD, 0xFFFF, 0x1234) == 0xABCD  # AND all ones: unchanged
    assert da.mask_write_result(0xABCD, 0x0000, 0x1234) == 0x1234  # AND zero: the OR mask
    assert da.mask_write_result(0xFFFF, 0x0000, 0x0000) == 0x0000


# --- FC24: FIFO count -------------------------------------------------------------------------------


def fifo_reply(count: int, byte_count: int | None = None) -> bytes:
    byte_count = 2 + 2 * count if byte_count is None else byte_count
    return struct.pack(">BHH", 0x18, byte_count, count) + bytes(2 * count)


def test_fifo_count_up_to_31():
    assert len(da.ReadFifoQueue(0).decode_response(fifo_reply(31)).registers) == 31
    assert da.ReadFifoQueue(0).decode_response(fifo_reply(0)).registers == ()


def test_fifo_count_over_31_is_refused():
    with pytest.raises(DecodeError):
        da.ReadFifoQueue(0).decode_response(fifo_reply(32))
    with pytest.raises(DecodeError):
        decode_response(fifo_reply(32))
    # A server holding 32 entries answers exception 03 instead of building such a reply.
    refused(VALUE, da.ReadFifoQueueResponse, (0,) * 32)


def test_fifo_byte_count_must_be_two_plus_twice_the_count():
    with pytest.raises(DecodeError):
        da.ReadFifoQueueResponse.decode(struct.pack(">BHH", 0x18, 8, 2) + bytes(6))
    with pytest.raises(DecodeError):
        da.ReadFifoQueueResponse.decode(struct.pack(">BHH", 0x18, 6, 3) + bytes(4))


def test_fifo_reply_length_is_told_by_its_two_byte_count():
    assert da.ReadFifoQueue.response_size.of(bytes.fromhex("18 00")) is None
    assert da.ReadFifoQueue.response_size.of(bytes.fromhex("18 00 08")) == 11


# --- FC20 / FC21: file records ---------------------------------------------------------------------


def test_file_numbers():
    assert fr.FileRecordRequest(1, 0, 1) and fr.FileRecordRequest(0xFFFF, 0, 1)
    refused(ADDRESS, fr.FileRecordRequest, 0, 0, 1)
    refused(ADDRESS, fr.FileRecordRequest, 0x10000, 0, 1)
    refused(ADDRESS, fr.FileRecord, 0, 0, (1,))


def test_record_numbers():
    assert fr.FileRecordRequest(1, 0x270F, 1).record == 9999
    refused(ADDRESS, fr.FileRecordRequest, 1, 0x2710, 1)
    refused(ADDRESS, fr.FileRecordRequest, 1, -1, 1)
    refused(ADDRESS, fr.FileRecordRequest, 1, 9999, 2)  # runs past record 9999
    refused(ADDRESS, fr.FileRecord, 1, 0x2710, (1,))
    refused(ADDRESS, fr.FileRecord, 1, 9998, (1, 2, 3))


def test_record_lengths_and_values():
    refused(VALUE, fr.FileRecordRequest, 1, 0, 0)
    refused(VALUE, fr.FileRecord, 1, 0, ())
    refused(VALUE, fr.FileRecord, 1, 0, (0x10000,))


def test_read_file_record_byte_count_0x07_to_0xf5():
    one = fr.FileRecordRequest(1, 0, 1)
    assert len(fr.ReadFileRecord((one,) * 35).groups) == 35  # 35 × 7 = 0xF5
    refused(VALUE, fr.ReadFileRecord, ())
    refused(VALUE, fr.ReadFileRecord, (one,) * 36)


def test_read_file_record_reply_must_fit():
    # 2 + 2 × 122 = 246 bytes of reply: more than 0xF5.
    refused(VALUE, fr.ReadFileRecord, (fr.FileRecordRequest(1, 0, 122),))
    assert fr.ReadFileRecord((fr.FileRecordRequest(1, 0, 121),))


def test_read_file_record_on_the_server_side():
    good = fr.ReadFileRecord((fr.FileRecordRequest(4, 1, 2),)).encode()
    assert fr.ReadFileRecord.decode(good).groups == (fr.FileRecordRequest(4, 1, 2),)
    refused(ADDRESS, fr.ReadFileRecord.decode, good[:2] + b"\x05" + good[3:])  # reference type 5
    refused(VALUE, fr.ReadFileRecord.decode, bytes.fromhex("14 06 06 0004 0001 00"))  # byte count 6
    refused(VALUE, fr.ReadFileRecord.decode, bytes.fromhex("14 08 06 0004 0001 0002 06"))  # not 7n
    refused(ADDRESS, fr.ReadFileRecord.decode, bytes.fromhex("14 07 06 0000 0001 0002"))  # file 0
    refused(ADDRESS, fr.ReadFileRecord.decode, bytes.fromhex("14 07 06 0001 2710 0001"))  # record 10000


def test_write_file_record_byte_count_0x09_to_0xfb():
    # One group of n registers is 7 + 2n bytes: n = 122 makes 0xFB, n = 123 one group too many.
    assert fr.WriteFileRecord((fr.FileRecord(1, 0, (0,) * 122),))
    refused(VALUE, fr.WriteFileRecord, (fr.FileRecord(1, 0, (0,) * 123),))
    refused(VALUE, fr.WriteFileRecord, ())


def test_write_file_record_on_the_server_side():
    good = fr.WriteFileRecord((fr.FileRecord(4, 7, (0x06AF, 0x04BE, 0x100D)),)).encode()
    assert good == bytes.fromhex("15 0D 06 0004 0007 0003 06AF 04BE 100D")
    refused(ADDRESS, fr.WriteFileRecord.decode, good[:2] + b"\x07" + good[3:])  # reference type 7
    # the group claims 4 registers but the byte count holds 3
    refused(VALUE, fr.WriteFileRecord.decode, good[:7] + b"\x00\x04" + good[9:])
    refused(VALUE, fr.WriteFileRecord.decode, bytes.fromhex("15 08 06 0004 0007 0000 00"))  # byte count 8


def test_read_file_record_reply_checks():
    request = fr.ReadFileRecord((fr.FileRecordRequest(4, 1, 2), fr.FileRecordRequest(3, 9, 2)))
    reply = bytes.fromhex("14 0C 05 06 0DFE 0020 05 06 33CD 0040")
    assert request.decode_response(reply).records == ((0x0DFE, 0x0020), (0x33CD, 0x0040))
    with pytest.raises(MismatchError):  # only one group answered
        request.decode_response(bytes.fromhex("14 06 05 06 0DFE 0020"))
    with pytest.raises(DecodeError):  # reference type 5
        request.decode_response(bytes.fromhex("14 0C 05 05 0DFE 0020 05 06 33CD 0040"))
    with pytest.raises(DecodeError):  # group length 4 is not 1 + 2n
        request.decode_response(bytes.fromhex("14 0C 04 06 0DFE 00 05 06 33CD 0040 00"))
    with pytest.raises(DecodeError):  # group runs past the byte count
        request.decode_response(bytes.fromhex("14 06 07 06 0DFE 0020"))


# --- FC08, FC11, FC12, FC17 -------------------------------------------------------------------------


def test_diagnostics_sub_functions_of_the_spec():
    sub = sl.DiagnosticSubFunction
    assert [int(s) for s in sub] == [0x00, 0x01, 0x02, 0x03, 0x04, *range(0x0A, 0x16)]
    assert sub.BUS_CHAR_OVERRUN_COUNT == 0x12  # seed 002 prints 00 11 for this row


def test_diagnostics_limits():
    assert sl.Diagnostics(0, bytes(MAX_PDU - 3))
    refused(VALUE, sl.Diagnostics, 0, bytes(MAX_PDU - 2))
    refused(VALUE, sl.Diagnostics, 0x10000)
    refused(VALUE, sl.Diagnostics, sl.Sub.BUS_MESSAGE_COUNT, b"\x00")  # known subs take 2 bytes


def test_force_listen_only_expects_no_response():
    assert sl.Diagnostics(sl.Sub.FORCE_LISTEN_ONLY).expects_response is False
    assert sl.Diagnostics(sl.Sub.RESTART_COMMUNICATIONS).expects_response is True


def test_diagnostics_reply_lengths():
    assert sl.Diagnostics(0, b"\x01\x02\x03\x04").response_length(b"\x08") == 7
    assert sl.Diagnostics(sl.Sub.BUS_MESSAGE_COUNT).response_length(b"\x08") == 5
    get = sl.Diagnostics(sl.Sub.MODBUS_PLUS_STATS, sl.MODBUS_PLUS_GET)
    assert get.response_length(bytes.fromhex("08 0015 0003")) is None
    assert get.response_length(bytes.fromhex("08 0015 0003 6C")) == 6 + 0x6C
    stats = bytes.fromhex("08 0015 0003 6C") + bytes(range(0x6C))
    reply = get.decode_response(stats)
    assert len(reply.statistics) == sl.MODBUS_PLUS_WORDS
    # No request at hand: the generic rule still reads the Modbus Plus byte count.
    assert sl.Diagnostics.response_size.of(stats) == len(stats)
    assert sl.Diagnostics.response_size.of(bytes.fromhex("08 000B 0010")) == 5


def test_diagnostics_reply_checks():
    with pytest.raises(MismatchError):  # another sub-function
        sl.Diagnostics(sl.Sub.BUS_MESSAGE_COUNT).decode_response(bytes.fromhex("08 000C 0001"))
    with pytest.raises(MismatchError):  # return query data must echo
        sl.Diagnostics(0, b"\xa5\x37").decode_response(bytes.fromhex("08 0000 A538"))
    count = sl.Diagnostics(sl.Sub.BUS_MESSAGE_COUNT).decode_response(bytes.fromhex("08 000B 0123"))
    assert count.value == 0x0123


def test_comm_event_counter_status():
    assert sl.CommEventCounterResponse.decode(bytes.fromhex("0B FFFF 0108")).busy
    idle = sl.CommEventCounterResponse.decode(bytes.fromhex("0B 0000 0108"))
    assert not idle.busy and idle.warnings == ()
    assert sl.CommEventCounterResponse.decode(bytes.fromhex("0B 1234 0108")).warnings


def test_comm_event_log_limits():
    assert len(sl.CommEventLogResponse.decode(bytes([0x0C, 6 + 64]) + bytes(6 + 64)).events) == 64
    with pytest.raises(DecodeError):  # 65 events
        sl.CommEventLogResponse.decode(bytes([0x0C, 6 + 65]) + bytes(6 + 65))
    with pytest.raises(DecodeError):  # byte count below 6
        sl.CommEventLogResponse.decode(bytes.fromhex("0C 04 0000 0000"))


@pytest.mark.parametrize(
    ("byte", "text"),
    [
        (0x00, "communications restart"),
        (0x04, "entered listen-only mode"),
        (0x20, "unrecognised event 0x20"),  # seed 002 reads it as listen-only; spec §5 does not
        (0x01, "unrecognised event 0x01"),
        (0x80, "receive event"),
        (0xC2, "receive event: communication error, broadcast received"),
        (0xB0, "receive event: character overrun, currently in listen-only mode"),
        (0x40, "send event"),
        (0x41, "send event: read exception sent (codes 1-3)"),
        (0x60, "send event: currently in listen-only mode"),
        (
            0x5E,
            "send event: slave abort exception sent (code 4), slave busy exception sent (codes 5-6),"
            " slave program NAK exception sent (code 7), write timeout error occurred",
        ),
    ],
)
def test_describe_event(byte, text):
    assert sl.describe_event(byte) == text


def test_describe_every_event_byte():
    for byte in range(256):
        assert sl.describe_event(byte)
    with pytest.raises(RequestError):
        sl.describe_event(256)


def test_report_slave_id_run_indicator():
    on = sl.ReportSlaveIdResponse.decode(bytes.fromhex("11 04 09 FF 0102"))
    assert (on.slave_id, on.run_indicator, on.extra, on.warnings) == (9, True, b"\x01\x02", ())
    off = sl.ReportSlaveIdResponse.decode(bytes.fromhex("11 02 03 00"))
    assert off.run_indicator is False and off.run_indicator_byte is None
    odd = sl.ReportSlaveIdResponse.decode(bytes.fromhex("11 02 03 01"))
    assert odd.run_indicator_byte == 0x01 and odd.warnings
    assert odd.encode() == bytes.fromhex("11 02 03 01")
    with pytest.raises(DecodeError):  # no room for the run indicator
        sl.ReportSlaveIdResponse.decode(bytes.fromhex("11 01 03"))


@pytest.mark.parametrize(
    "kind",
    [sl.ReadExceptionStatus, sl.Diagnostics, sl.GetCommEventCounter, sl.GetCommEventLog, sl.ReportSlaveId],
)
def test_serial_only_function_codes(kind):
    assert kind.serial_only


def test_data_access_is_not_serial_only():
    assert not da.ReadHoldingRegisters.serial_only and not da.ReadFifoQueue.serial_only


# --- FC43 / 0E: read device identification ----------------------------------------------------------


def test_device_id_read_codes_and_object_ids():
    for code in range(1, 5):
        assert di.ReadDeviceIdentification(code).read_code == code
    refused(VALUE, di.ReadDeviceIdentification, 0)
    refused(VALUE, di.ReadDeviceIdentification, 5)
    refused(ADDRESS, di.ReadDeviceIdentification, 4, 256)
    assert di.ReadDeviceIdentification(1).encode() == bytes.fromhex("2B 0E 01 00")


def test_device_id_on_the_server_side():
    assert di.ReadDeviceIdentification.decode(bytes.fromhex("2B 0E 04 05")).object_id == 5
    refused(VALUE, di.ReadDeviceIdentification.decode, bytes.fromhex("2B 0E 05 00"))
    refused(ExceptionCode.ILLEGAL_FUNCTION, di.ReadDeviceIdentification.decode, bytes.fromhex("2B 0D 01 00"))


REPLY = bytes.fromhex("2B 0E 01 01 00 00 03 00 04 41434D45 01 02 5831 02 03 312E30")


def test_device_id_reply():
    reply = di.ReadDeviceIdentification(1).decode_response(REPLY)
    assert reply.objects == ((0, b"ACME"), (1, b"X1"), (2, b"1.0"))
    assert reply.named_objects()[0] == ("VendorName", b"ACME")
    assert not reply.more_follows and reply.conformity_name.startswith("basic")
    assert di.object_name(0x06) == "UserApplicationName" and di.object_name(0x80) == "Private80"


def test_device_id_reply_length_walks_the_objects():
    size = di.ReadDeviceIdentification.response_size
    for cut in range(len(REPLY)):
        assert size.of(REPLY[:cut]) in (None, len(REPLY))
    assert size.of(REPLY[:7]) is None  # the header alone does not tell
    assert size.of(REPLY[:9]) is None  # one object header: still the others to come
    assert size.of(REPLY[:-1]) == len(REPLY)  # the last object header tells the end
    assert size.of(REPLY) == len(REPLY)


def test_device_id_reply_checks():
    with pytest.raises(MismatchError):  # read code 2 answered with read code 1
        di.ReadDeviceIdentification(2).decode_response(REPLY)
    single = bytes.fromhex("2B 0E 04 81 00 00 01 05 02 4142")
    assert di.ReadDeviceIdentification(4, 5).decode_response(single).objects == ((5, b"AB"),)
    with pytest.raises(MismatchError):  # asked for object 4, got object 5
        di.ReadDeviceIdentification(4, 4).decode_response(single)
    with pytest.raises(DecodeError):  # MEI type 0D
        di.ReadDeviceIdentification(1).decode_response(REPLY[:1] + b"\x0d" + REPLY[2:])
    with pytest.raises(DecodeError):  # an object runs past the end
        di.DeviceIdentificationResponse.decode(REPLY[:-1])
    with pytest.raises(DecodeError):  # bytes after the last object
        di.DeviceIdentificationResponse.decode(REPLY + b"\x00")


def test_device_id_more_follows_byte():
    more = bytes.fromhex("2B 0E 01 01 FF 02 00")
    assert di.DeviceIdentificationResponse.decode(more).more_follows
    odd = di.DeviceIdentificationResponse.decode(bytes.fromhex("2B 0E 01 01 01 02 00"))
    assert odd.more_follows and odd.warnings
