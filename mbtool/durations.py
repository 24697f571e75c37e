"""Durations on a link: round-trip times (the master's, link/stats.py) and response times (a bus
seen by the passive monitor, monitor/stats.py), kept one way for both.

A histogram with fixed buckets, one list for the whole program: a TCP device's milliseconds
and a 1200-baud line's seconds (a 256-byte reply alone takes 2.3 s there) land in the same
bins wherever they are counted, and an exporter shows them as they are
(``modbus_request_duration_seconds``).  Beside it, the figures a summary prints: min, avg and
max of every duration, mdev as ping(8) computes it, and the 95th percentile of the most recent.

Standard library only, so that both sides of the wire may import it (pyproject's contracts).
"""

from __future__ import annotations

import math
from bisect import bisect_left
from collections import deque

# Upper bounds in seconds, each bucket holding the durations up to its bound (Prometheus's
# "le"); one more bucket holds those past the last.  1 ms is a loopback TCP device, 10 s a
# slow gateway behind a 1200-baud line at its worst.
BUCKETS = (0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0)

# Durations kept for the 95th percentile: the most recent, so a run left going for weeks keeps
# a bounded window and a percentile of the device as it is now.
WINDOW = 1000


def percentile(values, fraction: float) -> float:
    """The nearest-rank percentile (``fraction`` of 1) of some values: the smallest value that at
    least that fraction of them do not exceed; every figure mbtool prints uses this rule."""
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, max(0, math.ceil(fraction * len(ordered)) - 1))]


class Durations:
    """Durations added up as they come: the histogram, their figures and the recent window."""

    def __init__(self) -> None:
        self.count = 0
        self.total = 0.0
        self.squares = 0.0  # the sum of their squares, for mdev
        self.low = math.inf
        self.high = 0.0
        self.counts = [0] * (len(BUCKETS) + 1)  # per bucket, not cumulative; the last: past 10 s
        self.recent: deque[float] = deque(maxlen=WINDOW)

    def add(self, seconds: float) -> None:
        self.count += 1
        self.total += seconds
        self.squares += seconds * seconds
        # Comparisons, not min() and max(): a poll runs this between a reply and its next request.
        if seconds < self.low:
            self.low = seconds
        if seconds > self.high:
            self.high = seconds
        self.counts[bisect_left(BUCKETS, seconds)] += 1
        self.recent.append(seconds)

    def merge(self, other: Durations) -> None:
        """Fold another's durations into these (a link's are its devices')."""
        self.count += other.count
        self.total += other.total
        self.squares += other.squares
        self.low = min(self.low, other.low)
        self.high = max(self.high, other.high)
        self.counts = [mine + theirs for mine, theirs in zip(self.counts, other.counts, strict=True)]
        self.recent.extend(other.recent)

    def buckets(self) -> list[tuple[float, int]]:
        """(upper bound, how many took at most that long), cumulative, the last bound infinity:
        a Prometheus histogram's buckets."""
        running, out = 0, []
        for bound, count in zip((*BUCKETS, math.inf), self.counts, strict=True):
            running += count
            out.append((bound, running))
        return out

    def mdev(self) -> float:
        """The mean deviation as ping(8) prints it: sqrt(mean of squares - square of the mean)."""
        if not self.count:
            return 0.0
        mean = self.total / self.count
        return math.sqrt(max(0.0, self.squares / self.count - mean * mean))

    def figures(self) -> dict[str, float] | None:
        """min, avg, p95 and max in seconds; None before the first duration."""
        if not self.count:
            return None
        return {
            "min": self.low,
            "avg": self.total / self.count,
            "p95": percentile(self.recent, 0.95),
            "max": self.high,
        }

    def cell(self) -> str:
        """min/avg/p95/max in ms to a tenth, for a column of a table: "4.2/4.8/5.7/5.7", or "-"
        before any."""
        figures = self.figures()
        if figures is None:
            return "-"
        return "/".join(f"{figures[name] * 1000:.1f}" for name in ("min", "avg", "p95", "max"))

    def text(self, names: tuple[str, ...] = ("min", "avg", "p95", "max")) -> str:
        """The figures named, in ms to the microsecond as ping(8) prints them:
        "min/avg/p95/max 1.204/3.417/5.600/7.815 ms", or "-" before any."""
        figures = self.figures()
        if figures is None:
            return "-"
        figures["mdev"] = self.mdev()
        shown = "/".join(f"{figures[name] * 1000:.3f}" for name in names)
        return f"{'/'.join(names)} {shown} ms"
