"""Framer robustness: garbage before a frame, frames back to back, truncated frames (spec §2)."""

from __future__ import annotations

import random

import pytest
from helpers.frames import drain_events, settle_events

from mbtool.codec import data_access as da
from mbtool.codec import device_id as di
from mbtool.codec import serial_line as sl
from mbtool.codec.ascii import AsciiFramer
from mbtool.codec.errors import ChecksumError, FrameError
from mbtool.codec.exchange import Exchange
from mbtool.codec.framer import Frame, Rejected
from mbtool.codec.mbap import TcpFramer
from mbtool.codec.pdu import UNKNOWN
from mbtool.codec.rtu import RtuFramer

REQUEST = da.ReadHoldingRegisters(107, 3)
REPLY = da.RegistersResponse(3, (555, 0, 100))
UNIT = 0x11


def frames(events) -> list[Frame]:
    return [event for event in events if isinstance(event, Frame)]


def garbage(n: int, seed: int) -> bytes:
    return random.Random(seed).randbytes(n)


@pytest.mark.parametrize("seed", range(8))
@pytest.mark.parametrize("n", [1, 16, 256])
@pytest.mark.parametrize("responses", [True, False], ids=["reply", "request"])
@pytest.mark.parametrize("framer_type", [RtuFramer, AsciiFramer], ids=["rtu", "ascii"])
def test_garbage_before_a_frame(framer_type, responses, n, seed):
    framer = framer_type(responses=responses)
    pdu = (REPLY if responses else REQUEST).encode()
    adu = framer.build(UNIT, pdu)
    noise = garbage(n, seed)
    framer.feed(noise + adu)
    events = drain_events(framer)  # no silence needed: the frame ends by its own length
    assert frames(events) == [Frame(UNIT, pdu, adu)]
    assert events[-1] == Frame(UNIT, pdu, adu)
    rejected = b"".join(event.data for event in events if isinstance(event, Rejected))
    assert rejected == noise
    assert framer.buffered == 0


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("framer_type", [RtuFramer, AsciiFramer], ids=["rtu", "ascii"])
def test_garbage_before_a_frame_fed_byte_by_byte(framer_type, seed):
    framer = framer_type(responses=True)
    framer.expect = REQUEST
    adu = framer.build(UNIT, REPLY.encode())
    noise = garbage(64, seed)
    events = []
    for byte in noise + adu:
        framer.feed(bytes([byte]))
        events += drain_events(framer)
    assert events[-1] == Frame(UNIT, REPLY.encode(), adu)
    assert len(frames(events)) == 1


def test_garbage_whose_length_cannot_be_told_does_not_hold_up_a_frame():
    # A noise byte then 17 (unit 23) reads as the head of an FC23 request, whose byte count
    # would sit past the end of the real, shorter request behind it.
    framer = RtuFramer(responses=False)
    adu = framer.build(0x17, REQUEST.encode())
    framer.feed(b"\x42" + adu)
    events = drain_events(framer)
    assert events[-1] == Frame(0x17, REQUEST.encode(), adu)


@pytest.mark.parametrize("framer_type", [RtuFramer, AsciiFramer, TcpFramer], ids=["rtu", "ascii", "tcp"])
def test_two_frames_back_to_back(framer_type):
    framer = framer_type(responses=True)
    first = framer.build(UNIT, REPLY.encode(), 1)
    second = framer.build(UNIT + 1, da.RegistersResponse(3, (1,)).encode(), 2)
    framer.feed(first + second)
    events = drain_events(framer)
    assert [event.adu for event in events] == [first, second]
    assert all(isinstance(event, Frame) for event in events)


@pytest.mark.parametrize("framer_type", [RtuFramer, AsciiFramer], ids=["rtu", "ascii"])
def test_a_frame_after_a_bad_one(framer_type):
    framer = framer_type(responses=True)
    good = framer.build(UNIT, REPLY.encode())
    bad = bytearray(good)
    bad[-3] ^= 0x01  # a data byte (RTU) or an LRC digit (ASCII) changed on the way
    framer.feed(bytes(bad) + good)
    events = drain_events(framer)
    assert events[-1] == Frame(UNIT, REPLY.encode(), good)
    assert isinstance(events[0], Rejected)


@pytest.mark.parametrize("cut", [1, 2, 5, 10])
@pytest.mark.parametrize("framer_type", [RtuFramer, AsciiFramer, TcpFramer], ids=["rtu", "ascii", "tcp"])
def test_truncated_frame_is_rejected_on_silence(framer_type, cut):
    framer = framer_type(responses=True)
    adu = framer.build(UNIT, REPLY.encode(), 5)
    framer.feed(adu[:-cut])
    assert drain_events(framer) == []  # waiting for the rest
    events = settle_events(framer)
    assert events and all(isinstance(event, Rejected) for event in events)
    assert all(isinstance(event.error, FrameError) for event in events)
    assert b"".join(event.data for event in events) == adu[:-cut]


def test_rtu_frame_cut_short_is_called_truncated_not_a_crc_error():
    framer = RtuFramer(responses=True)
    framer.expect = da.ReadHoldingRegisters(0, 1)
    framer.feed(bytes.fromhex("01 03 02 00 64"))  # a 7-byte reply whose CRC never came
    events = settle_events(framer)
    assert all(isinstance(event, Rejected) for event in events)
    assert b"".join(event.data for event in events) == bytes.fromhex("01 03 02 00 64")
    # the first verdict is on the whole: what the client reports
    assert not isinstance(events[0].error, ChecksumError)
    assert str(events[0].error) == "truncated frame (5 of 7 bytes)"


def test_rtu_frame_with_an_unknown_function_code_ends_on_silence():
    framer = RtuFramer(responses=True)
    adu = framer.build(UNIT, bytes.fromhex("41 01 02 03"))

    class Raw(da.ReadFifoQueue):  # stands for a raw request of a function code the codec does not know
        function_code = 0x41

        def response_length(self, pdu):
            return UNKNOWN

    framer.expect = Raw(0)
    framer.feed(adu)
    assert drain_events(framer) == []
    assert framer.waiting_for_silence
    assert framer.silence() == Frame(UNIT, bytes.fromhex("41 01 02 03"), adu)


def test_rtu_ends_a_reply_by_the_request_length_rule():
    # A return-query-data echo of 6 data bytes: the class rule alone would assume 2.
    request = sl.Diagnostics(0, bytes(range(6)))
    framer = RtuFramer(responses=True)
    framer.expect = request
    adu = framer.build(UNIT, request.encode())
    framer.feed(adu + b"\x00")
    assert framer.next_event() == Frame(UNIT, request.encode(), adu)


def test_rtu_device_identification_reply_in_pieces():
    reply = di.DeviceIdentificationResponse(1, 0x81, False, 0, ((0, b"ACME"), (1, b"X1"), (2, b"1.0")))
    framer = RtuFramer(responses=True)
    adu = framer.build(UNIT, reply.encode())
    for i in range(0, len(adu), 3):
        framer.feed(adu[i : i + 3])
        events = drain_events(framer)
        if i + 3 < len(adu):
            assert events == []
    assert events == [Frame(UNIT, reply.encode(), adu)]


def test_exception_reply_is_framed_for_every_function_code():
    framer = RtuFramer(responses=True)
    adu = framer.build(UNIT, bytes.fromhex("AB 01"))  # FC43 | 0x80, illegal function
    framer.feed(adu)
    assert framer.next_event() == Frame(UNIT, bytes.fromhex("AB 01"), adu)


def test_bad_crc_carries_received_and_expected():
    framer = RtuFramer(responses=False)
    framer.feed(bytes.fromhex("11 03 00 6B 00 03 87 76"))  # CRC sent high byte first: wrong
    event = settle_events(framer)[0]
    assert isinstance(event.error, ChecksumError)
    assert (event.error.expected, event.error.received) == (0x8776, 0x7687)


MODBUS_TCP_DEVICE = "the device speaks Modbus TCP: leave --framer out"


@pytest.mark.parametrize(
    "request_, unit, reply",
    [
        # pymodbus read "01 03 00 00 00 02 C4 0B" as MBAP: transaction 0x0103, protocol 0,
        # length 2, unit 0xC4, FC 0B, and answered the comm event counter (issue 39.3).
        (da.ReadHoldingRegisters(0, 2), 1, "01 03 0000 0006 C4 0B 0000 0000"),
        # mbtool serve read "4D 03 00 00 00 02 CA 07" as FC 07 to unit 0xCA.
        (da.ReadHoldingRegisters(0, 2), 77, "4D 03 0000 0003 CA 07 6D"),
        # A write's reply, whose RTU length the function code alone tells (8 bytes).
        (da.WriteSingleRegister(0, 2), 1, "01 06 0000 0003 08 8B 01"),
    ],
)
def test_an_mbap_reply_to_an_rtu_request_says_the_device_speaks_modbus_tcp(request_, unit, reply):
    framer = RtuFramer()
    framer.expect, framer.expect_unit = request_, unit
    data = bytes.fromhex(reply)
    framer.feed(data)
    events = settle_events(framer)
    # One rejection, of the whole MBAP frame: the trace's line is the error's.
    assert len(events) == 1 and isinstance(events[0], Rejected), events
    assert MODBUS_TCP_DEVICE in str(events[0].error) and not isinstance(events[0].error, ChecksumError)
    assert events[0].data == data


def _broken(frame: bytes) -> bytes:
    """The frame with its CRC's high byte changed, as noise does."""
    return frame[:-1] + bytes([frame[-1] ^ 0xFF])


@pytest.mark.parametrize(
    "request_, reply",
    [
        # The echo of a write to register 0, its CRC broken: its first seven bytes are those of
        # an MBAP header answering it (length: the value), but the frame is not that long.
        (da.WriteSingleRegister(0, 2), _broken(RtuFramer().build(1, da.WriteSingleRegister(0, 2).encode()))),
        (da.WriteSingleRegister(0, 3), _broken(RtuFramer().build(1, da.WriteSingleRegister(0, 3).encode()))),
        (da.ReadHoldingRegisters(0, 2), _broken(RtuFramer().build(1, bytes.fromhex("03 04 0064 0065")))),
        # Another unit's bytes in front of a Modbus TCP answer's.
        (da.ReadHoldingRegisters(0, 2), bytes.fromhex("02 03 0000 0006 C4 0B 0000 0000")),
        # A request of four bytes is no MBAP header: nothing answers it as one (found by fuzzing).
        (sl.GetCommEventCounter(), bytes.fromhex("01 0B 0000 000A 260C 7E71 17A5 1DF1 874F 30F9")),
    ],
)
def test_a_reply_with_a_bad_crc_is_not_taken_for_modbus_tcp(request_, reply):
    framer = RtuFramer()
    framer.expect, framer.expect_unit = request_, 1
    framer.feed(reply)
    events = settle_events(framer)
    assert events and not any(MODBUS_TCP_DEVICE in str(event.error) for event in events), events


def test_ascii_with_a_changed_delimiter():
    framer = AsciiFramer(responses=False, delimiter=ord("!"))
    adu = framer.build(UNIT, REQUEST.encode())
    assert adu.endswith(b"\r!")
    framer.feed(adu)
    assert framer.next_event() == Frame(UNIT, REQUEST.encode(), adu)


def test_tcp_length_field_out_of_range_is_rejected():
    framer = TcpFramer(responses=True)
    framer.feed(bytes.fromhex("0001 0000 0001 11"))  # length 1: a unit id and no PDU
    events = settle_events(framer)
    assert events and all(isinstance(event, Rejected) for event in events)


class _Parsing(TcpFramer):
    """An MBAP framer that tells whether it was handed bytes to parse."""

    parsed = False

    def feed(self, data: bytes) -> None:
        self.parsed = True
        super().feed(data)


def _taken_as_predicted(data: bytes, request=REQUEST, before: bytes = b"") -> bool:
    """Whether an exchange that sent ``request`` (transaction 7), its framer holding ``before``,
    takes ``data``, the read after the request, as the reply predicted: whole, unparsed."""
    framer = _Parsing()
    exchange = Exchange(framer)
    if before:  # what an earlier transaction's read left in the framer
        exchange.attempt(UNIT, request, fresh=True)
        exchange.receive(before)
    exchange.transaction_id = 6
    exchange.attempt(UNIT, request, fresh=not before)
    framer.parsed = False
    try:
        reply = exchange.receive(data)
    except FrameError:
        return False
    return reply is not None and not framer.parsed


def test_tcp_predicts_exactly_the_reply_asked_for_and_nothing_else():
    tcp = TcpFramer()
    pdu = REPLY.encode()
    reply = tcp.build(UNIT, pdu, 7)
    expected = tcp.predict(UNIT, REQUEST.reply_prefix)
    assert expected is not None
    request = tcp.frames(UNIT, REQUEST.encode())(7)
    assert reply.startswith(request[: expected.repeated] + expected.head)  # its transaction id, then
    assert len(reply) == expected.size and reply[expected.pdu_at :] == pdu  # its size, where its PDU starts
    tcp.feed(reply)
    assert tcp.next_event() == Frame(UNIT, pdu, reply, 7)  # what the parse finds in it
    unlike = {
        "another unit": tcp.build(UNIT + 1, pdu, 7),
        "another transaction": tcp.build(UNIT, pdu, 8),
        "an exception": tcp.build(UNIT, bytes.fromhex("83 02"), 7),
        "another byte count, same size": tcp.build(UNIT, bytes([3, 4]) + pdu[2:], 7),
        "cut short": reply[:-1],
        "two replies in one read": reply + reply,
        "an empty read (an echo held back)": b"",
    }
    for why, data in unlike.items():
        assert not _taken_as_predicted(data), why
    assert _taken_as_predicted(reply)
    assert not _taken_as_predicted(reply, before=b"\x00"), "bytes already buffered come first"
    assert not _taken_as_predicted(reply, da.WriteSingleRegister(1, 2))  # not a read: nothing predicted
    assert tcp.predict(UNIT, da.WriteSingleRegister(1, 2).reply_prefix) is None


def test_tcp_parses_replies_that_came_in_one_read_in_turn():
    framer = TcpFramer()
    pdu = REPLY.encode()
    reply, later = framer.build(UNIT, pdu, 7), framer.build(UNIT, pdu, 9)
    framer.feed(reply + reply + later)
    assert framer.buffered == 3 * len(reply)
    assert drain_events(framer) == [
        Frame(UNIT, pdu, reply, 7),
        Frame(UNIT, pdu, reply, 7),
        Frame(UNIT, pdu, later, 9),
    ]
    assert framer.buffered == 0
    framer.feed(reply)
    framer.reset()  # another request
    assert framer.buffered == 0 and framer.next_event() is None


def test_corrupted_reply_is_held_until_silence_then_rejected_whole():
    # Its last byte might be the unit of the real reply: only a pause on the line can tell.
    framer = RtuFramer(responses=True)
    framer.expect = REQUEST
    good = framer.build(UNIT, REPLY.encode())
    bad = good[:-1] + bytes([good[-1] ^ 0xFF])
    framer.feed(bad)
    assert drain_events(framer) == []
    assert framer.waiting_for_silence
    event = framer.silence()
    assert isinstance(event, Rejected) and isinstance(event.error, ChecksumError)
    assert event.data == bad
    assert framer.silence() is None and framer.buffered == 0


def test_reply_starting_on_the_last_byte_of_a_phantom_frame_is_kept():
    # 61 16 ...: noise that reads as an FC22 frame of 10 bytes, ending on the reply's unit byte.
    framer = RtuFramer(responses=True)
    framer.expect = REQUEST
    adu = framer.build(UNIT, REPLY.encode())
    noise = bytes.fromhex("61 16 C6 E9 C9 2D 99 BF 35")
    framer.feed(noise + adu[:1])
    assert drain_events(framer) == []
    framer.feed(adu[1:])
    events = drain_events(framer)
    assert events[-1] == Frame(UNIT, REPLY.encode(), adu)
    assert b"".join(event.data for event in events[:-1]) == noise


def test_the_framings_face_gives_every_envelope_name_and_loads_only_what_is_asked_for():
    """Issue 30: one module an envelope, codec/framing.py on top.  Its names are the modules'
    own, and taking the base's or the registry's imports no envelope (a one-shot read's
    start-up pays for its own framing only)."""
    import subprocess
    import sys

    from mbtool.codec import ascii, framer, framing, mbap, resync, rtu

    for name, module in framing._DEFINED_IN.items():
        assert getattr(framing, name) is getattr(
            {"rtu": rtu, "ascii": ascii, "mbap": mbap, "resync": resync}[module], name
        )
    for name in ("Frame", "Framer", "Rejected", "Event"):
        assert getattr(framing, name) is getattr(framer, name)
    assert not hasattr(framing, "NoSuchFramer")
    script = (
        "import sys\n"
        "from mbtool.codec.framing import Frame, Framer, Rejected, make_framer\n"
        "make_framer('tcp')\n"
        "print(' '.join(sorted(m for m in sys.modules if m.startswith('mbtool.codec.'))))"
    )
    loaded = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, check=True
    ).stdout.split()
    assert "mbtool.codec.mbap" in loaded
    assert not {"mbtool.codec.rtu", "mbtool.codec.ascii", "mbtool.codec.resync"} & set(loaded)


def test_a_frame_is_a_value_that_cannot_be_changed():
    frame = Frame(UNIT, REPLY.encode(), b"raw", 5)
    assert frame == Frame(unit=UNIT, pdu=REPLY.encode(), adu=b"raw", transaction_id=5)
    assert hash(frame) == hash(Frame(UNIT, REPLY.encode(), b"raw", 5))
    assert Frame(UNIT, b"", b"").transaction_id is None  # RTU and ASCII carry none
    with pytest.raises(AttributeError):
        frame.unit = 2
