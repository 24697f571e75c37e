"""The resync search (codec/resync.py) on its own, with a toy framing for the judge: each
offset is judged once for good, or again only once the bytes that decide it have come;
positions stay true while the buffer's front is dropped; and garbage costs linear time.

The RTU framers and the bus monitor build on it: tests/test_resync.py and tests/test_monitor.py
test them through garbage.
"""

from __future__ import annotations

from mbtool.codec.resync import FRAME, NO_FRAME, FrameSearch, Verdict


class Toy:
    """A stream in a toy framing: a frame is ``F``, its length n (a digit), then n - 2 more
    bytes; any other byte starts none.  Judgements are counted, by absolute position."""

    def __init__(self) -> None:
        self.buffer = bytearray()
        self.fed = 0  # bytes fed so far
        self.judged: list[int] = []
        self.search = FrameSearch()

    @property
    def base(self) -> int:
        return self.fed - len(self.buffer)

    def feed(self, data: bytes) -> None:
        self.buffer += data
        self.fed += len(data)

    def drop(self, count: int) -> None:
        del self.buffer[:count]

    def judge(self, offset: int) -> Verdict | int:
        self.judged.append(self.base + offset)
        buf = self.buffer
        if buf[offset] != ord("F"):
            return NO_FRAME
        if offset + 1 >= len(buf):
            return self.base + offset + 2  # its length has not come
        end = offset + int(chr(buf[offset + 1]))
        return FRAME if end <= len(buf) else self.base + end

    def starts(self, lo: int, hi: int):
        return range(lo, hi)

    def find(self, end: int | None = None) -> int | None:
        end = len(self.buffer) if end is None else end
        return self.search.find(self.base, self.fed, end, end, self.judge, self.starts)


def test_the_first_frame_behind_the_front_is_found():
    toy = Toy()
    toy.feed(b"xyF3zF4ab")
    assert toy.find() == 2
    assert toy.judged == [1, 2]  # offset 0 is the front: the framer judges it itself


def test_an_offset_judged_for_good_is_never_judged_again():
    toy = Toy()
    toy.feed(b"xyz")
    assert toy.find() is None
    toy.feed(b"wvF4ab")
    assert toy.find() == 5
    assert toy.judged == [1, 2, 3, 4, 5]


def test_a_pending_offset_waits_for_the_bytes_that_decide_it():
    toy = Toy()
    toy.feed(b"xF5a")  # a frame of 5 starts at 1: two bytes short
    assert toy.find() is None
    toy.feed(b"b")  # one short: the offset is not judged again yet
    assert toy.find() is None
    assert toy.judged.count(1) == 1
    toy.feed(b"c")
    assert toy.find() == 1
    assert toy.judged.count(1) == 2


def test_a_frame_is_searched_for_only_up_to_the_end_given():
    toy = Toy()
    toy.feed(b"xyF2")
    assert toy.find(end=2) is None  # offset 2 lies beyond: not judged
    assert toy.judged == [1]
    assert toy.find() == 2


def test_positions_stay_true_when_the_front_is_dropped():
    toy = Toy()
    toy.feed(b"xyzF5a")  # pending at 3, until position 8
    assert toy.find() is None
    toy.drop(2)  # garbage handed out: the buffer now starts at position 2
    toy.feed(b"bc")
    assert toy.find() == 1  # position 3, one byte behind the new front
    assert sorted(set(toy.judged)) == [1, 2, 3, 4, 5]


def test_pending_offsets_dropped_with_the_front_are_forgotten():
    toy = Toy()
    toy.feed(b"xF9abc")  # pending at 1
    assert toy.find() is None
    toy.drop(3)  # position 1 is gone
    toy.feed(b"defgh")
    assert toy.find() is None
    assert toy.judged.count(1) == 1


def test_reset_forgets_every_judgement():
    toy = Toy()
    toy.feed(b"xyz")
    toy.find()
    toy.search.reset()  # what decides a verdict changed (another request)
    toy.find()
    assert toy.judged == [1, 2, 1, 2]


def test_garbage_fed_byte_by_byte_is_judged_once_an_offset():
    toy = Toy()
    garbage = bytes(b"ab" * 5000)
    for byte in garbage:
        toy.feed(bytes([byte]))
        assert toy.find() is None
    assert len(toy.judged) == len(garbage) - 1
    assert len(set(toy.judged)) == len(toy.judged)
