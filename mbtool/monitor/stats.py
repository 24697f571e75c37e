"""A bus's statistics from what the passive monitor saw, per unit (issue 32): which device is
sick, without sending a byte.

They count frames seen, not transactions made (those are link/stats.py's): for each unit its
requests, its replies, its exceptions by code, its requests left unanswered, the frames with
its address and a bad CRC/LRC (the wire), its response time (from the end of a request to the
start of its reply, ``BusFrame.latency``) and the frames that started less than t3.5 after the
one before them (spec §2: a master or a device breaking the line's silence).  For the bus: its
frames, its garbage and its utilisation, the time the line carried bytes over the time watched.

A gap is only as fine as the port lets the monitor see it: an adapter that delivers bytes in
bursts (a USB chip's latency timer) hands over two frames in one read, and they count as a
break.  Fed a recording with no time stamps, there is no time to measure: response times,
breaks and utilisation are None.
"""

from __future__ import annotations

from collections import Counter

from mbtool.codec.errors import exceptions_by_code, exceptions_text
from mbtool.durations import Durations
from mbtool.monitor.bus import BusFrame, Unanswered
from mbtool.words import counted


class UnitStats:
    """What one unit's frames came to."""

    def __init__(self) -> None:
        self.requests = 0  # with a good checksum; a broadcast counts for unit 0
        self.replies = 0  # with a good checksum, not exceptions
        self.exceptions: Counter[int] = Counter()  # exception code -> count
        self.unanswered = 0
        self.corrupt = 0  # frames with its address and a bad checksum, either way
        self.breaks = 0  # its frames that started less than t3.5 after the one before
        self.response = Durations()  # end of request to start of reply (exceptions too)

    def as_dict(self, timed: bool, t35: bool) -> dict:
        return {
            "requests": self.requests,
            "replies": self.replies,
            "exceptions_by_code": exceptions_by_code(self.exceptions),
            "unanswered": self.unanswered,
            "corrupt": self.corrupt,
            "t35_breaks": self.breaks if timed and t35 else None,
            "response_seconds": self.response.figures(),
        }


class BusStats:
    """Every frame and unanswered request the monitor reports, counted as it comes.

    ``t35``: the line's t3.5 in seconds (None for ASCII, which has none: spec §2);
    ``char_time``: seconds one character takes on the line; ``timed``: the times are when
    the bytes came (False for a recording of raw bytes); ``started``: when watching began
    (None: at the first frame, as for a recording).
    """

    def __init__(self, t35: float | None, char_time: float, timed: bool = True, started: float | None = None):
        self.t35 = t35
        self.char_time = char_time
        self.timed = timed
        self.started = started
        self.last = started  # when the last byte seen came
        self.units: dict[int, UnitStats] = {}
        self.frames = 0
        self.garbage_bytes = 0
        self.breaks = 0
        self.busy = 0.0  # seconds of bytes on the line

    def count(self, seen: BusFrame | Unanswered) -> None:
        if isinstance(seen, Unanswered):
            self._unit(seen.request.unit).unanswered += 1
            return
        if self.started is None:
            self.started = seen.time
        self.last = seen.end if self.last is None else max(self.last, seen.end)
        self.busy += len(seen.wire) * self.char_time
        if seen.direction == "garbage":
            self.garbage_bytes += len(seen.wire)
            return
        self.frames += 1
        unit = self._unit(seen.unit)
        if self.t35 is not None and seen.gap is not None and seen.gap < self.t35:
            self.breaks += 1
            unit.breaks += 1
        if not seen.checksum_ok:
            unit.corrupt += 1
        elif seen.direction == "request":
            unit.requests += 1
        else:
            if "exception" in seen.flags:
                assert seen.described is not None  # an exception was read from its fields
                pdu = seen.described.pdu
                unit.exceptions[pdu[1] if len(pdu) > 1 else 0] += 1
            else:
                unit.replies += 1
            if seen.latency is not None:
                unit.response.add(seen.latency)

    def _unit(self, unit: int | None) -> UnitStats:
        assert unit is not None  # every frame but garbage has its unit
        stats = self.units.get(unit)
        if stats is None:
            stats = self.units[unit] = UnitStats()
        return stats

    def seconds(self, now: float | None = None) -> float | None:
        """The time watched: from the start to ``now`` (None: the last byte seen)."""
        if not self.timed or self.started is None:
            return None
        end = now if now is not None else self.last
        return max(0.0, (end if end is not None else self.started) - self.started)

    def utilisation(self, now: float | None = None) -> float | None:
        """The fraction of the time watched that the line carried bytes."""
        seconds = self.seconds(now)
        if not seconds:
            return None
        return min(1.0, self.busy / seconds)

    def as_dict(self, now: float | None = None) -> dict:
        timed, t35 = self.timed, self.t35 is not None
        return {
            "seconds": self.seconds(now),
            "frames": self.frames,
            "garbage_bytes": self.garbage_bytes,
            "t35_breaks": self.breaks if timed and t35 else None,
            "utilisation": self.utilisation(now),
            "units": [
                {"unit": unit, **stats.as_dict(timed, t35)} for unit, stats in sorted(self.units.items())
            ],
        }

    def table(self, now: float | None = None) -> list[str]:
        """The statistics as aligned lines: a row a unit, then the bus."""
        head = ["unit", "requests", "replies", "exceptions", "unanswered", "corrupt", "t3.5 breaks",
                "response min/avg/p95/max ms"]  # fmt: skip
        rows = [head]
        for unit, stats in sorted(self.units.items()):
            response = stats.response.cell()
            exceptions = exceptions_text(stats.exceptions)
            breaks = str(stats.breaks) if self.timed and self.t35 is not None else "-"
            rows.append([str(unit), str(stats.requests), str(stats.replies), exceptions, str(stats.unanswered),
                         str(stats.corrupt), breaks, response])  # fmt: skip
        widths = [max(len(row[i]) for row in rows) for i in range(len(head))]
        lines = [
            "  ".join(cell.ljust(w) for cell, w in zip(row, widths, strict=True)).rstrip() for row in rows
        ]
        bus = f"bus: {counted(self.frames, 'frame')}, {counted(self.garbage_bytes, 'garbage byte')}"
        if self.timed and self.t35 is not None:
            bus += f", {counted(self.breaks, 't3.5 break')}"
        utilisation, seconds = self.utilisation(now), self.seconds(now)
        if utilisation is not None:
            bus += f", utilisation {100 * utilisation:.1f}% over {seconds:.1f} s"
        return [*lines, bus]
