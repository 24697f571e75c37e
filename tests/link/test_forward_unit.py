"""The bridge's core (mbtool.link.forward.Forwarder) request by request, in-process.

Requests come as a device-side framer hands them over; the link behind is mbtool's own
Client on test_client's scripted link and fake clock, so the gateway's answers (the device's
reply passed on, 0A, 0B, refusals without the bus) are checked without a socket or a line.
"""

from __future__ import annotations

import contextlib

import pytest
from helpers.fakes import FakeClock, ScriptedLink
from helpers.frames import mbap, rtu

from mbtool.codec.framing import Frame, Rejected, RtuFramer, device_framer
from mbtool.errors import ConnectionFailed
from mbtool.link.client import Client
from mbtool.link.forward import (
    BROADCAST,
    INVALID,
    NO_PATH,
    NO_RESPONSE,
    REFUSED,
    REPLY,
    Forwarder,
    Passage,
)
from mbtool.link.transport import ConnectionClosed

PEER = "127.0.0.1:40000"
READ = "03 0000 0001"  # FC03, one register from 0
READ_REPLY = "03 02 002A"


class Links:
    """``open_link`` for the forwarder: each opening is a Client on the next link given;
    with none left, the link cannot be opened."""

    def __init__(self, clock: FakeClock, *links: ScriptedLink) -> None:
        self.clock = clock
        self.links = list(links)
        self.opened = 0
        self.closed = 0

    @contextlib.contextmanager
    def __call__(self):
        self.opened += 1
        if not self.links:
            raise ConnectionFailed("cannot open /dev/ttyUSB9: no such device")
        link = self.links.pop(0)
        try:
            yield Client(link, RtuFramer(), timeout=0.5, clock=self.clock, sleep=self.clock.sleep)
        finally:
            self.closed += 1


class ClosingLink(ScriptedLink):
    """A link whose device has closed the connection: the next write finds it gone."""

    def __init__(self, clock: FakeClock, replies: list[list[bytes]], answered: int) -> None:
        super().__init__(clock, replies)
        self.answered = answered

    def write(self, data: bytes) -> None:
        if len(self.written) >= self.answered:
            raise ConnectionClosed("tcp://192.0.2.10:502 closed the connection")
        super().write(data)


def link(clock: FakeClock, *replies: str | None) -> ScriptedLink:
    """A link answering each request with an RTU frame of these hex bytes (None: silence)."""
    return ScriptedLink(clock, [[] if text is None else [rtu(bytes.fromhex(text))] for text in replies])


def forwarder(links: Links, units=frozenset({1, 2}), **options) -> tuple[Forwarder, list[Passage]]:
    passages: list[Passage] = []
    return Forwarder(links, "rtu", units, passages.append, **options), passages


def ask(gateway: Forwarder, framing: str, unit: int, pdu: str, transaction_id: int = 7) -> bytes | None:
    """The gateway's answer to a request as it comes in from a client in this framing."""
    framer = device_framer(framing)
    framer.feed(framer.build(unit, bytes.fromhex(pdu), transaction_id))
    event = framer.next_event() or framer.silence()  # silence ends a frame of unknown length
    assert isinstance(event, Frame)
    return gateway.answer(event, framer, PEER)


def H(text: str) -> bytes:
    return bytes.fromhex(text)


# --- what goes on the bus, and what comes back ----------------------------------------------


def test_the_device_s_reply_goes_back_unchanged_in_the_client_s_framing():
    clock = FakeClock()
    bus = link(clock, "01 " + READ_REPLY)
    gateway, passages = forwarder(Links(clock, bus))
    assert ask(gateway, "tcp", 1, READ, transaction_id=0x1234) == mbap(0x1234, 1, H(READ_REPLY))
    assert bus.written == [rtu(H("01 " + READ))]
    (passage,) = passages
    assert passage.outcome == REPLY and passage.why == ""
    assert (passage.peer, passage.unit, passage.function) == (PEER, 1, 3)
    assert passage.request == mbap(0x1234, 1, H(READ))
    assert (passage.upstream, passage.downstream) == ("tcp", "rtu")
    assert passage.sent == rtu(H("01 " + READ))
    assert passage.received == rtu(H("01 " + READ_REPLY))
    assert passage.reply == mbap(0x1234, 1, H(READ_REPLY))
    assert passage.bus_time is not None and passage.bus_time >= 0
    assert passage.total >= 0


def test_a_device_s_exception_goes_back_as_it_is():
    clock = FakeClock()
    gateway, passages = forwarder(Links(clock, link(clock, "01 83 02")))
    assert ask(gateway, "tcp", 1, READ) == mbap(7, 1, H("83 02"))
    assert passages[0].outcome == REFUSED
    assert "exception 02" in passages[0].why


def test_a_request_no_reply_is_due_for_gets_none():
    clock = FakeClock()
    bus = link(clock)  # FC08 sub 04 (force listen-only) is never answered (spec §4)
    gateway, passages = forwarder(Links(clock, bus))
    assert ask(gateway, "tcp", 1, "08 0004 0000") is None
    assert bus.written == [rtu(H("01 08 0004 0000"))]
    assert (passages[0].outcome, passages[0].why, passages[0].reply) == (REPLY, "no reply is due", b"")


# --- 0B: the device did not respond ------------------------------------------------------


def test_silence_is_answered_0B_and_the_unit_is_then_answered_0B_without_the_bus():
    clock = FakeClock()
    bus = link(clock, None, "02 " + READ_REPLY)
    gateway, passages = forwarder(Links(clock, bus), silent_hold=60.0)
    assert ask(gateway, "tcp", 1, READ) == mbap(7, 1, H("83 0B"))
    assert passages[0].outcome == NO_RESPONSE
    assert "no response from unit 1" in passages[0].why
    assert ask(gateway, "tcp", 1, READ) == mbap(7, 1, H("83 0B"))  # held: the bus is not asked
    assert len(bus.written) == 1
    assert passages[1].outcome == NO_RESPONSE and passages[1].sent == b""
    assert "unit 1 did not respond" in passages[1].why and "(--silent-hold)" in passages[1].why
    assert ask(gateway, "tcp", 2, READ) == mbap(7, 2, H(READ_REPLY))  # another unit still goes
    assert len(bus.written) == 2


def test_silent_hold_0_asks_the_bus_every_time():
    clock = FakeClock()
    bus = link(clock, None, "01 " + READ_REPLY)
    gateway, _ = forwarder(Links(clock, bus), silent_hold=0.0)
    assert ask(gateway, "tcp", 1, READ) == mbap(7, 1, H("83 0B"))
    assert ask(gateway, "tcp", 1, READ) == mbap(7, 1, H(READ_REPLY))
    assert len(bus.written) == 2


def test_a_garbled_reply_is_answered_0B_and_the_unit_is_not_held():
    clock = FakeClock()
    garbled = rtu(H("01 " + READ_REPLY))[:-1] + b"\x00"
    bus = ScriptedLink(clock, [[garbled], [rtu(H("01 " + READ_REPLY))]])
    gateway, passages = forwarder(Links(clock, bus), silent_hold=60.0)
    assert ask(gateway, "tcp", 1, READ) == mbap(7, 1, H("83 0B"))
    assert passages[0].outcome == NO_RESPONSE
    assert "CRC" in passages[0].why
    # Something came: the unit is there, so it is asked again at once.
    assert ask(gateway, "tcp", 1, READ) == mbap(7, 1, H(READ_REPLY))
    assert len(bus.written) == 2


# --- 0A: no path ----------------------------------------------------------------------------


def test_a_unit_not_forwarded_is_answered_0A_over_tcp_and_left_to_other_slaves_on_a_line():
    clock = FakeClock()
    bus = link(clock)
    gateway, passages = forwarder(Links(clock, bus), units=frozenset({1}))
    assert ask(gateway, "tcp", 5, READ) == mbap(7, 5, H("83 0A"))
    assert ask(gateway, "rtu", 5, READ) is None
    assert bus.written == []
    assert [p.outcome for p in passages] == [NO_PATH, NO_PATH]
    assert passages[0].why == "unit 5 is not forwarded (--units)"
    assert passages[1].reply == b""


def test_a_link_that_cannot_be_opened_is_answered_0A_and_opened_again_for_the_next():
    clock = FakeClock()
    links = Links(clock)
    gateway, passages = forwarder(links)
    assert ask(gateway, "tcp", 1, READ) == mbap(7, 1, H("83 0A"))
    assert passages[0].outcome == NO_PATH
    assert passages[0].why == "cannot open /dev/ttyUSB9: no such device"
    links.links.append(link(clock, "01 " + READ_REPLY))  # plugged back in
    assert ask(gateway, "tcp", 1, READ) == mbap(7, 1, H(READ_REPLY))
    assert links.opened == 2


def test_a_link_the_device_closed_is_opened_once_more_for_the_same_request():
    clock = FakeClock()
    first = ClosingLink(clock, [[rtu(H("01 " + READ_REPLY))]], answered=1)
    links = Links(clock, first, link(clock, "01 " + READ_REPLY))
    gateway, _ = forwarder(links)
    assert ask(gateway, "tcp", 1, READ) == mbap(7, 1, H(READ_REPLY))
    assert ask(gateway, "tcp", 1, READ, transaction_id=8) == mbap(8, 1, H(READ_REPLY))
    assert (links.opened, links.closed) == (2, 1)


def test_a_new_link_that_closes_at_once_is_not_tried_again():
    clock = FakeClock()
    links = Links(clock, ClosingLink(clock, [], answered=0), link(clock, "01 " + READ_REPLY))
    gateway, passages = forwarder(links)
    assert ask(gateway, "tcp", 1, READ) == mbap(7, 1, H("83 0A"))
    assert passages[0].outcome == NO_PATH
    assert "closed the connection" in passages[0].why
    assert links.opened == 1


def test_open_and_close_open_the_link_before_any_request_and_close_it():
    clock = FakeClock()
    links = Links(clock, link(clock, "01 " + READ_REPLY))
    gateway, _ = forwarder(links)
    gateway.open()
    assert links.opened == 1
    assert ask(gateway, "tcp", 1, READ) == mbap(7, 1, H(READ_REPLY))
    assert links.opened == 1  # the link opened beforehand serves the request
    gateway.close()
    assert links.closed == 1


def test_open_raises_when_the_link_cannot_be_opened():
    gateway, _ = forwarder(Links(FakeClock()))
    with pytest.raises(ConnectionFailed, match="no such device"):
        gateway.open()


# --- what never goes on the bus ---------------------------------------------------------------


@pytest.mark.parametrize(
    "pdu, reply",
    [
        ("03 0000 0000", "83 03"),  # a count of 0: no device could take it
        ("41 0102", "C1 01"),  # a function code the codec does not know
        ("03 FFFF 0002", "83 02"),  # past address 65535
    ],
)
def test_a_request_no_device_could_take_is_answered_as_a_device_would_without_the_bus(pdu, reply):
    clock = FakeClock()
    bus = link(clock)
    gateway, passages = forwarder(Links(clock, bus))
    assert ask(gateway, "tcp", 1, pdu) == mbap(7, 1, H(reply))
    assert bus.written == []
    assert passages[0].outcome == INVALID and passages[0].why.startswith("not forwarded: ")


def test_raw_functions_forwards_a_function_code_the_codec_does_not_know():
    clock = FakeClock()
    bus = ScriptedLink(clock, [[rtu(H("01 41 0102 03"))]])
    gateway, passages = forwarder(Links(clock, bus), raw_functions=True)
    assert ask(gateway, "tcp", 1, "41 0102") == mbap(7, 1, H("41 0102 03"))
    assert bus.written == [rtu(H("01 41 0102"))]
    assert passages[0].outcome == REPLY


def test_bytes_that_make_no_request_get_nothing_and_no_passage():
    clock = FakeClock()
    bus = link(clock)
    gateway, passages = forwarder(Links(clock, bus))
    framer = device_framer("rtu")
    framer.feed(rtu(H("01 " + READ))[:-1] + b"\x00")  # a bad CRC
    event = framer.next_event() or framer.silence()
    assert isinstance(event, Rejected)
    assert gateway.answer(event, framer, PEER) is None
    assert passages == [] and bus.written == []


# --- broadcasts (spec §2) ---------------------------------------------------------------------


def test_a_broadcast_write_from_a_line_is_forwarded_and_answered_by_none():
    clock = FakeClock()
    bus = link(clock)
    gateway, passages = forwarder(Links(clock, bus), units=frozenset({0, 1}))
    assert ask(gateway, "rtu", 0, "06 0001 0003") is None
    assert bus.written == [rtu(H("00 06 0001 0003"))]
    assert passages[0].outcome == BROADCAST
    assert passages[0].why == "sent to every unit, answered by none"


def test_a_broadcast_read_is_not_forwarded():
    clock = FakeClock()
    bus = link(clock)
    gateway, passages = forwarder(Links(clock, bus), units=frozenset({0, 1}))
    assert ask(gateway, "rtu", 0, READ) is None
    assert bus.written == []
    assert passages[0].outcome == INVALID
    assert passages[0].why == "not forwarded: only writes are broadcast (spec §2)"


def test_a_tcp_client_s_unit_0_is_the_broadcast_of_the_line_behind():
    clock = FakeClock()
    bus = link(clock)
    gateway, passages = forwarder(Links(clock, bus), units=frozenset({0}))
    assert ask(gateway, "tcp", 0, "06 0001 0003") is None
    assert bus.written == [rtu(H("00 06 0001 0003"))]
    assert passages[0].outcome == BROADCAST


def test_a_broadcast_not_among_the_units_is_not_forwarded():
    clock = FakeClock()
    bus = link(clock)
    gateway, passages = forwarder(Links(clock, bus), units=frozenset({1}))
    assert ask(gateway, "rtu", 0, "06 0001 0003") is None
    assert bus.written == []
    assert passages[0].outcome == NO_PATH
