"""The transaction layer against a scripted fake link and a fake clock (unit tests may use fakes)."""

from __future__ import annotations

import pytest
from helpers.fakes import FakeClock, ScriptedLink

from mbtool.codec.ascii import AsciiFramer
from mbtool.codec.checksum import crc_bytes
from mbtool.codec.data_access import ReadHoldingRegisters, WriteSingleRegister
from mbtool.codec.errors import ChecksumError, FrameError, MismatchError, ModbusException
from mbtool.codec.mbap import TcpFramer
from mbtool.codec.rtu import RtuFramer
from mbtool.codec.timing import character_bits, silent_interval
from mbtool.errors import NoResponse
from mbtool.link.client import Client, Trace
from mbtool.link.transport import ConnectionClosed


def rtu(hex_text: str) -> bytes:
    body = bytes.fromhex(hex_text)
    return body + crc_bytes(body)


def client(link: ScriptedLink, clock: FakeClock, framer=None, **options) -> Client:
    return Client(link, framer or RtuFramer(), clock=clock, sleep=clock.sleep, **options)


REQUEST = ReadHoldingRegisters(0x6B, 3)
REPLY = rtu("11 03 06 02 2B 00 00 00 64")  # seed 002 fig. 15


def test_reply_in_one_chunk():
    clock = FakeClock()
    link = ScriptedLink(clock, [[REPLY]])
    assert client(link, clock).execute(0x11, REQUEST).registers == (555, 0, 100)
    assert link.written == [rtu("11 03 00 6B 00 03")]


def test_reply_dripped_byte_by_byte():
    clock = FakeClock()
    link = ScriptedLink(clock, [[bytes([b]) for b in REPLY]])
    assert client(link, clock).execute(0x11, REQUEST).registers == (555, 0, 100)


def test_noise_before_the_reply_is_skipped():
    clock = FakeClock()
    link = ScriptedLink(clock, [[b"\x00\xff\x11", REPLY]])
    assert client(link, clock).execute(0x11, REQUEST).registers == (555, 0, 100)


def test_silence_is_a_timeout_at_the_deadline():
    clock = FakeClock()
    link = ScriptedLink(clock, [[]])
    start = clock.now
    with pytest.raises(NoResponse, match="no response from unit 17 within 0.5 s"):
        client(link, clock, timeout=0.5).execute(0x11, REQUEST)
    assert 0.5 <= clock.now - start < 0.6


def test_retries_resend_and_the_second_answer_counts():
    clock = FakeClock()
    link = ScriptedLink(clock, [[], [REPLY]])
    assert client(link, clock, retries=1).execute(0x11, REQUEST).registers == (555, 0, 100)
    assert len(link.written) == 2


def test_bad_crc_is_an_invalid_response_not_a_timeout():
    clock = FakeClock()
    corrupted = REPLY[:-1] + bytes([REPLY[-1] ^ 0xFF])
    link = ScriptedLink(clock, [[corrupted]])
    start = clock.now
    with pytest.raises(ChecksumError):
        client(link, clock, timeout=5).execute(0x11, REQUEST)
    assert clock.now - start < 1, "a complete bad frame should not wait out the whole timeout"


def test_reply_from_another_unit_is_discarded_then_reported():
    clock = FakeClock()
    other = rtu("12 03 06 02 2B 00 00 00 64")
    link = ScriptedLink(clock, [[other]])
    with pytest.raises(MismatchError, match="unit 18, expected unit 17"):
        client(link, clock).execute(0x11, REQUEST)


def test_stale_reply_then_the_right_one():
    clock = FakeClock()
    stale = rtu("11 03 02 00 01")  # a reply to an earlier, shorter request
    link = ScriptedLink(clock, [[rtu("12 06 00 01 00 03"), REPLY]])
    assert client(link, clock).execute(0x11, REQUEST).registers == (555, 0, 100)
    link = ScriptedLink(clock, [[stale]])
    with pytest.raises(MismatchError):
        client(link, clock).execute(0x11, REQUEST)


def test_exception_reply_raises_with_its_name():
    clock = FakeClock()
    link = ScriptedLink(clock, [[rtu("11 83 02")]])
    with pytest.raises(ModbusException, match="02 Illegal Data Address"):
        client(link, clock).execute(0x11, REQUEST)


def test_busy_is_retried_when_the_timeout_would_have_ended():
    """Exception 06 Server Device Busy: retry later (spec §3), spaced as after silence."""
    clock = FakeClock()
    link = ScriptedLink(clock, [[rtu("11 83 06")], [REPLY]])
    start = clock.now
    assert client(link, clock, retries=1, timeout=0.5).execute(0x11, REQUEST).registers == (555, 0, 100)
    assert clock.now - start >= 0.5
    link = ScriptedLink(clock, [[rtu("11 83 06")]])
    with pytest.raises(ModbusException, match="06 Server Device Busy"):
        client(link, clock, retries=0).execute(0x11, REQUEST)
    link = ScriptedLink(clock, [[rtu("11 83 02")], [REPLY]])
    with pytest.raises(ModbusException, match="02 Illegal Data Address"):  # not retried
        client(link, clock, retries=1).execute(0x11, REQUEST)


def test_broadcast_returns_once_sent():
    clock = FakeClock()
    link = ScriptedLink(clock, [[]])
    start = clock.now
    assert client(link, clock).execute(0, WriteSingleRegister(1, 3)) is None
    assert clock.now - start < 0.01


def test_t35_silence_between_frames():
    clock = FakeClock()
    link = ScriptedLink(clock, [[REPLY], [REPLY]])
    c = client(link, clock, baud=9600)
    c.execute(0x11, REQUEST)
    c.execute(0x11, REQUEST)
    # 3.5 characters of 11 bits at 9600 baud, measured from the end of the reply
    assert clock.sleeps and clock.sleeps[-1] == pytest.approx(3.5 * 11 / 9600, rel=0.01)
    assert silent_interval(115200) == 0.00175


def test_t35_on_an_8n1_line_is_three_and_a_half_10_bit_characters():
    """Spec §2: a character is 11 bits in the spec's formats; 8N1 (which many devices ship)
    sends 10, and its t3.5 is 3.5 of those."""
    assert character_bits("E", 8, 1) == character_bits("N", 8, 2) == 11
    assert character_bits("N", 8, 1) == 10
    assert character_bits("E", 7, 1) == 10  # ASCII's 7E1
    clock = FakeClock()
    link = ScriptedLink(clock, [[REPLY], [REPLY]])
    c = client(link, clock, baud=9600, char_bits=character_bits("N", 8, 1))
    c.execute(0x11, REQUEST)
    c.execute(0x11, REQUEST)
    assert clock.sleeps[-1] == pytest.approx(3.5 * 10 / 9600, rel=0.01)
    assert silent_interval(115200, 10) == 0.00175  # the fixed value above 19200 baud


def test_echo_is_stripped():
    clock = FakeClock()
    sent = rtu("11 03 00 6B 00 03")
    link = ScriptedLink(clock, [[sent[:3], sent[3:] + REPLY[:4], REPLY[4:]]])
    assert client(link, clock, echo=True).execute(0x11, REQUEST).registers == (555, 0, 100)


def test_with_echo_bytes_that_are_not_the_echo_are_the_reply():
    """--echo on a link that does not echo: the device's reply is the reply (issue 12.14),
    not a bad echo that swallows it."""
    clock = FakeClock()
    link = ScriptedLink(clock, [[REPLY[:3], REPLY[3:]]])
    assert client(link, clock, echo=True).execute(0x11, REQUEST).registers == (555, 0, 100)


def test_with_echo_a_write_answered_by_its_copy_strips_only_the_echo():
    """FC06's reply is a copy of the request: with --echo the first copy is the echo."""
    clock = FakeClock()
    write = WriteSingleRegister(1, 3)
    sent = rtu("11 06 00 01 00 03")
    link = ScriptedLink(clock, [[sent, sent]])
    assert client(link, clock, echo=True).execute(0x11, write) == write
    link = ScriptedLink(clock, [[sent]])  # only the echo: no reply
    with pytest.raises(NoResponse):
        client(link, clock, echo=True).execute(0x11, write)


def test_tcp_transaction_ids_are_matched():
    clock = FakeClock()
    framer = TcpFramer()
    old = framer.build(0x11, bytes.fromhex("03 06 02 2B 00 00 00 63"), 7)
    ours = framer.build(0x11, bytes.fromhex("03 06 02 2B 00 00 00 64"), 1)
    link = ScriptedLink(clock, [[old + ours]], serial_line=False)
    assert client(link, clock, framer=TcpFramer()).execute(0x11, REQUEST).registers == (555, 0, 100)
    assert clock.sleeps == [], "no t3.5 on TCP"


def test_tcp_looks_for_stale_bytes_only_after_a_transaction_that_did_not_end_cleanly():
    """MBAP tells a stale reply by its transaction id, so a polling loop skips the look
    (a system call a poll) after a clean transaction; after a timeout it looks again."""
    clock = FakeClock()
    framer = TcpFramer()

    def reply(tid):
        return [framer.build(0x11, bytes.fromhex("03 06 02 2B 00 00 00 64"), tid)]

    class CountingLink(ScriptedLink):
        looks = 0

        def discard_input(self) -> bytes:
            self.looks += 1
            return b""

    link = CountingLink(clock, [reply(1), reply(2), [], reply(4), reply(5)], serial_line=False)
    tcp = client(link, clock, framer=TcpFramer(), timeout=0.5)
    looks = []
    for _ in range(2):
        tcp.execute(0x11, REQUEST)
        looks.append(link.looks)
    with pytest.raises(NoResponse):
        tcp.execute(0x11, REQUEST)
    looks.append(link.looks)
    for _ in range(2):
        tcp.execute(0x11, REQUEST)
        looks.append(link.looks)
    assert looks == [1, 1, 1, 2, 2]


def test_tcp_a_copy_of_the_reply_left_after_a_clean_transaction_is_told_by_its_id_next_time():
    """After a clean MBAP transaction the framer keeps what came after the reply (as the
    socket keeps what comes later): the next request's reply is matched by its transaction
    id, and the copy is discarded, traced as the old transaction's."""
    clock = FakeClock()
    framer = TcpFramer()
    first = framer.build(0x11, bytes.fromhex("03 06 02 2B 00 00 00 64"), 1)
    second = framer.build(0x11, bytes.fromhex("03 06 02 2B 00 00 00 65"), 2)
    link = ScriptedLink(clock, [[first + first], [second]], serial_line=False)

    class Notes(Trace):
        def __init__(self) -> None:
            self.seen: list[tuple[bytes, str]] = []

        def received(self, adu: bytes, note: str = "") -> None:
            self.seen.append((adu, note))

    notes = Notes()
    tcp = client(link, clock, framer=TcpFramer(), trace=notes)
    assert tcp.execute(0x11, REQUEST).registers == (555, 0, 100)
    assert tcp.execute(0x11, REQUEST).registers == (555, 0, 101)
    assert notes.seen == [
        (first, ""),
        (first, "reply has transaction id 1, expected 2"),
        (second, ""),
    ]


def test_endless_garbage_ends_at_the_deadline():
    clock = FakeClock()

    class Garbage(ScriptedLink):
        def read(self, timeout: float) -> bytes:
            clock.now += 0.01
            return bytes(range(0x20, 0x60))

    link = Garbage(clock, [[]])
    start = clock.now
    with pytest.raises(FrameError):
        client(link, clock, timeout=0.5).execute(0x11, REQUEST)
    assert clock.now - start < 0.6


# -- what the misbehaving-peer matrix (test_peer_matrix.py) showed -----------------------


def test_stale_reply_of_our_unit_with_another_count_is_discarded():
    """RTU has no transaction id: a reply that does not fit (two registers for three asked)
    is the late answer to an earlier request, not the end of this one."""
    clock = FakeClock()
    stale = rtu("11 03 04 00 0A 00 0B")
    link = ScriptedLink(clock, [[stale, REPLY]])
    assert client(link, clock, timeout=0.5).execute(0x11, REQUEST).registers == (555, 0, 100)
    assert len(link.written) == 1


def test_tcp_reply_with_our_transaction_id_and_a_wrong_byte_count_fails_at_once():
    clock = FakeClock()
    framer = TcpFramer()
    wrong = framer.build(0x11, bytes.fromhex("03 02 00 01"), 1)
    link = ScriptedLink(clock, [[wrong]], serial_line=False)
    start = clock.now
    with pytest.raises(MismatchError, match="byte count 2 does not fit 3 registers"):
        client(link, clock, framer=TcpFramer(), timeout=5).execute(0x11, REQUEST)
    assert clock.now - start < 1


class PausingLink(ScriptedLink):
    """A float among the chunks is a pause of that many seconds on the line."""

    def read(self, timeout: float) -> bytes:
        if self.pending and isinstance(self.pending[0], float):
            pause = self.pending.pop(0)
            self.clock.now += min(pause, timeout)
            if pause > timeout:
                self.pending.insert(0, pause - timeout)
            return b""
        return super().read(timeout)


@pytest.mark.parametrize("framer_type", [RtuFramer, AsciiFramer])
def test_echo_without_the_option_is_skipped_and_the_reply_taken(framer_type):
    """The echo at once, the reply after the device's turnaround: the echo is not judged as a reply
    (RTU: a CRC error; ASCII: a valid frame whose byte count is nonsense)."""
    clock = FakeClock()
    sent = framer_type().build(0x11, REQUEST.encode())
    reply = framer_type().build(0x11, REPLY[1:-2])
    link = PausingLink(clock, [[sent[:3], sent[3:], 0.2, reply[:2], reply[2:]]])
    c = client(link, clock, framer=framer_type(), timeout=0.5)
    assert c.execute(0x11, REQUEST).registers == (555, 0, 100)
    assert len(link.written) == 1


def test_only_the_echo_is_an_invalid_response_and_says_so():
    clock = FakeClock()
    link = ScriptedLink(clock, [[rtu("11 03 00 6B 00 03")]])
    with pytest.raises(FrameError, match="the only reply was a copy of the request.*--echo"):
        client(link, clock, timeout=0.5).execute(0x11, REQUEST)


def test_a_write_whose_reply_is_a_copy_of_the_request_is_not_taken_for_an_echo():
    clock = FakeClock()
    request = WriteSingleRegister(1, 3)
    sent = rtu("11 06 00 01 00 03")
    link = ScriptedLink(clock, [[sent]])
    start = clock.now
    assert client(link, clock, timeout=0.5).execute(0x11, request) == request.decode_response(sent[1:-2])
    assert clock.now - start < 0.1, "the reply was held back as if it were an echo"


def test_a_reply_that_starts_like_the_request_is_not_held_back():
    """Bytes held as a possible echo go to the framer as soon as they differ from the request."""
    clock = FakeClock()
    request = ReadHoldingRegisters(0x0200, 1)  # request 11 03 02 00 ..., reply 11 03 02 ...
    reply = rtu("11 03 02 00 07")
    link = ScriptedLink(clock, [[reply[:3], reply[3:]]])
    start = clock.now
    assert client(link, clock, timeout=0.5).execute(0x11, request).registers == (7,)
    assert clock.now - start < 0.1


class ClosingLink(ScriptedLink):
    """Sends the scripted chunks, then hangs up."""

    def read(self, timeout: float) -> bytes:
        if self.pending:
            return self.pending.pop(0)
        raise ConnectionClosed("tcp://device closed the connection")


def test_a_link_closed_mid_frame_is_not_retried_and_names_what_came():
    clock = FakeClock()
    link = ClosingLink(clock, [[REPLY[:3]], [REPLY]])
    with pytest.raises(ConnectionClosed, match="closed the connection; what it sent before: truncated"):
        client(link, clock, retries=2).execute(0x11, REQUEST)
    assert len(link.written) == 1, "a retry on a closed link can only fail to write"


def test_a_link_closed_before_replying_is_no_response():
    clock = FakeClock()
    link = ClosingLink(clock, [[], [REPLY]])
    with pytest.raises(ConnectionClosed, match="^tcp://device closed the connection$"):
        client(link, clock, retries=2).execute(0x11, REQUEST)
    assert len(link.written) == 1


def test_after_retries_the_most_telling_problem_is_reported_not_the_last():
    """A CRC error on the first attempt says more about the bus than silence on the retry."""
    clock = FakeClock()
    corrupted = REPLY[:-1] + bytes([REPLY[-1] ^ 0xFF])
    link = ScriptedLink(clock, [[corrupted], []])
    with pytest.raises(ChecksumError):
        client(link, clock, retries=1, timeout=0.5).execute(0x11, REQUEST)
    assert len(link.written) == 2
    link = ScriptedLink(clock, [[], [corrupted]])
    with pytest.raises(ChecksumError):
        client(link, clock, retries=1, timeout=0.5).execute(0x11, REQUEST)


def test_the_same_reply_bytes_give_the_same_response_and_other_bytes_a_new_one():
    """A poll whose reply is byte for byte the one before gets the response decoded then
    (responses are immutable); a reply that differs, or another request, is decoded anew,
    and a repeated exception reply still raises every time."""
    clock = FakeClock()
    other = rtu("11 03 06 02 2B 00 00 00 65")
    refusal = rtu("11 83 02")
    link = ScriptedLink(clock, [[REPLY], [REPLY], [other], [refusal], [refusal], [REPLY]])
    master = client(link, clock)
    first = master.execute(0x11, REQUEST)
    assert master.execute(0x11, REQUEST) is first
    changed = master.execute(0x11, REQUEST)
    assert changed is not first and changed.registers == (555, 0, 101)
    for _ in range(2):
        with pytest.raises(ModbusException, match="02 Illegal Data Address"):
            master.execute(0x11, REQUEST)
    again = master.execute(0x11, ReadHoldingRegisters(0x6B, 3))  # an equal request, not this one
    assert again == first and again is not first


class RecordingTrace(Trace):
    def __init__(self) -> None:
        self.lines: list[tuple] = []

    def sent(self, adu: bytes) -> None:
        self.lines.append(("sent", adu))

    def received(self, adu: bytes, note: str = "") -> None:
        self.lines.append(("received", adu, note))

    def rejected(self, data: bytes, error: FrameError) -> None:
        self.lines.append(("rejected", data, str(error)))


def test_a_tcp_reply_read_whole_is_taken_as_predicted_with_the_response_and_trace_of_a_parse():
    """A read that is exactly the reply the request predicts is taken without the framer (the
    MBAP framer's prediction, issue 41.9); the reply read in two pieces goes to the framer and
    is parsed.  Both end alike: the same response, the same trace."""
    reply = TcpFramer().build(0x11, bytes.fromhex("03 06 02 2B 00 00 00 64"), 1)

    class CountingFramer(TcpFramer):
        fed = 0

        def feed(self, data: bytes) -> None:
            self.fed += 1
            super().feed(data)

    ends = []
    for chunks, fed in (([reply], 0), ([reply[:8], reply[8:]], 2)):
        clock, trace, framer = FakeClock(), RecordingTrace(), CountingFramer()
        link = ScriptedLink(clock, [chunks], serial_line=False)
        response = client(link, clock, framer=framer, trace=trace).execute(0x11, REQUEST)
        ends.append((response, trace.lines))
        assert framer.fed == fed
    assert ends[0] == ends[1]
    assert ends[0][0].registers == (555, 0, 100)
    assert ends[0][1][-1] == ("received", reply, "")


def test_a_tcp_reply_unlike_the_prediction_is_judged_as_ever():
    """Another unit with our transaction id: not the reply predicted, so the judge sees it
    and says what is wrong, and --lenient still takes it."""
    other_unit = TcpFramer().build(0x12, bytes.fromhex("03 06 02 2B 00 00 00 64"), 1)
    clock = FakeClock()
    link = ScriptedLink(clock, [[other_unit]], serial_line=False)
    with pytest.raises(MismatchError, match="reply from unit 18, expected unit 17"):
        client(link, clock, framer=TcpFramer(), timeout=0.5).execute(0x11, REQUEST)
    link = ScriptedLink(clock, [[other_unit]], serial_line=False)
    lenient = client(link, clock, framer=TcpFramer(), lenient=True)
    assert lenient.execute(0x11, REQUEST).registers == (555, 0, 100)
    assert lenient.deviations == {"reply from unit 18, expected unit 17": None}
