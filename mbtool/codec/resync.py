"""The resync search: where a whole frame starts inside a buffer that may hold garbage before
it.  The search remembers what was judged at each offset; the RTU framers (``codec/rtu.py``)
and the bus monitor (``monitor/bus.py``) judge an offset each by their own rules.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable


class Verdict:
    """What judging one offset as a frame start tells, when it tells for good."""

    def __init__(self, name: str) -> None:
        self.name = name

    def __repr__(self) -> str:
        return self.name


FRAME = Verdict("FRAME")  # a whole frame with a good CRC starts here
NO_FRAME = Verdict("NO_FRAME")  # none starts here, whatever bytes follow
# Any other verdict is an int: the stream position the bytes must reach before it can tell.


class FrameSearch:
    """Where a whole RTU frame with a good CRC starts inside a buffer: resync (spec §2: an
    RTU frame has no start mark; only its length rule and its CRC tell one).  The master's
    and the device's framers and the bus monitor all search with it.

    Positions are absolute stream positions (bytes are only ever appended at the end and
    dropped at the front, so a position's bytes never change).  Each offset is judged once
    for good, or kept pending until the bytes that decide it have come, and only judged
    again then: garbage costs linear time (without it each byte of garbage rescanned the
    whole buffer, and 64 KiB took a second).
    """

    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        """Forget every judgement: what decides a verdict has changed (another request)."""
        self.scanned = 0  # every position below it has been judged...
        self.pending: list[tuple[int, int]] = []  # ...and these may still start a frame: (position, wake)

    def find(
        self,
        base: int,
        fed: int,
        end: int,
        last: int,
        judge: Callable[[int], Verdict | int],
        starts: Callable[[int, int], Iterable[int]],
    ) -> int | None:
        """The first offset in 1..end-1 where ``judge`` (given an offset into the buffer, whose
        first byte is at stream position ``base``; ``fed`` bytes so far) finds a frame.
        New offsets are taken from ``starts(lo, hi)`` up to ``last``: the others are not worth
        judging (yet)."""
        pending = self.pending
        if pending and pending[0][0] <= base:
            pending = [entry for entry in pending if entry[0] > base]
        still = []
        for index, entry in enumerate(pending):
            position, wake = entry
            if position >= base + end:
                still += pending[index:]
                break
            if wake > fed:
                still.append(entry)  # the bytes that decide it have not all come
                continue
            verdict = judge(position - base)
            if verdict is FRAME:
                self.pending = still + pending[index + 1 :]
                return position - base
            if not isinstance(verdict, Verdict):  # not NO_FRAME: where to judge it again
                still.append((position, verdict))
        self.pending = still
        first = max(self.scanned - base, 1)
        if first < last:
            for start in starts(first, last):
                verdict = judge(start)
                if verdict is FRAME:
                    self.scanned = base + start + 1
                    return start
                if not isinstance(verdict, Verdict):  # not NO_FRAME
                    self.pending.append((base + start, verdict))
            self.scanned = base + last
        return None
