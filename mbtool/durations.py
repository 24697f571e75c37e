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
import operator
import threading
from bisect import bisect_right
from collections import deque
from contextlib import contextmanager

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
    """Durations added up as they come: the histogram, their figures and the recent window.

    A polling loop adds one a transaction, so adding is an append to a batch; the batch is
    folded into the sums, the extremes, the histogram and the window by C loops (sorted, sum,
    bisect over the sorted batch) when it is full or when anything is read.  A transaction
    then pays for an append, not for a dozen updates and a bisect of its own.

    Another thread may read while one adds (a plant's live view, its exporter): a fold and
    every read hold a lock, and a fold takes the durations batched so far and removes just
    those, so an append that comes meanwhile (without the lock) stays for the next fold,
    none is counted twice and a reader sees every figure of the same folds."""

    def __init__(self) -> None:
        self._count = 0
        self._total = 0.0
        self._squares = 0.0  # the sum of their squares, for mdev
        self._low = math.inf
        self._high = 0.0
        self._counts = [0] * (len(BUCKETS) + 1)  # per bucket, not cumulative; the last: past 10 s
        self._recent: deque[float] = deque(maxlen=WINDOW)
        self._batch: list[float] = []  # added since the last fold, in the order they came
        self._folding = threading.Lock()

    def add(self, seconds: float) -> None:
        batch = self._batch
        batch.append(seconds)
        if len(batch) >= WINDOW:  # bounded, however long nothing reads them
            with self._folding:
                self._fold()

    def _fold(self) -> None:
        """Add the batch to the figures; the caller holds the lock."""
        batch = self._batch
        taken = batch[:]  # one C call each, as an append is: appends since stay in the batch
        if not taken:
            return
        del batch[: len(taken)]
        ordered = sorted(taken)
        self._count += len(ordered)
        self._total += sum(ordered)
        self._squares += sum(map(operator.mul, ordered, ordered))
        self._low = min(self._low, ordered[0])
        self._high = max(self._high, ordered[-1])
        # Bucket i holds the durations above bound i-1 up to bound i (Prometheus's "le").
        below = 0
        for bucket, bound in enumerate(BUCKETS):
            upto = bisect_right(ordered, bound)
            self._counts[bucket] += upto - below
            below = upto
        self._counts[-1] += len(ordered) - below
        self._recent.extend(taken)

    @contextmanager
    def _folded(self):
        """What every reader reads within: the lock held, the batch folded in."""
        with self._folding:
            self._fold()
            yield

    @property
    def count(self) -> int:
        with self._folded():
            return self._count

    @property
    def total(self) -> float:
        with self._folded():
            return self._total

    @property
    def high(self) -> float:
        with self._folded():
            return self._high

    @property
    def recent(self) -> list[float]:
        """The most recent WINDOW durations, oldest first (the 95th percentile's)."""
        with self._folded():
            return list(self._recent)

    def copy(self) -> Durations:
        """These durations as they are now, in a Durations of its own (a record's, for readers
        on other threads): taken whole, not merged into an empty one, and the batch with them,
        folded when the copy is read (a plant copies its counts every poll, reads them seldom)."""
        copy = Durations()
        with self._folding:
            copy._count, copy._total, copy._squares = self._count, self._total, self._squares
            copy._low, copy._high, copy._counts = self._low, self._high, list(self._counts)
            copy._recent.extend(self._recent)
            copy._batch = self._batch[:]
        return copy

    def merge(self, other: Durations, recent: bool = True) -> None:
        """Fold another's durations into these (a link's are its devices'); ``recent=False``
        leaves the window out (the exporter's link totals show no percentile)."""
        with other._folded():
            count, total, squares = other._count, other._total, other._squares
            low, high, counts = other._low, other._high, list(other._counts)
            window = list(other._recent) if recent else []
        with self._folded():
            self._count += count
            self._total += total
            self._squares += squares
            self._low = min(self._low, low)
            self._high = max(self._high, high)
            self._counts = [mine + their for mine, their in zip(self._counts, counts, strict=True)]
            self._recent.extend(window)

    def buckets(self) -> list[tuple[float, int]]:
        """(upper bound, how many took at most that long), cumulative, the last bound infinity:
        a Prometheus histogram's buckets."""
        with self._folded():
            counts = list(self._counts)
        running, out = 0, []
        for bound, count in zip((*BUCKETS, math.inf), counts, strict=True):
            running += count
            out.append((bound, running))
        return out

    def mdev(self) -> float:
        """The mean deviation as ping(8) prints it: sqrt(mean of squares - square of the mean)."""
        with self._folded():
            if not self._count:
                return 0.0
            mean = self._total / self._count
            return math.sqrt(max(0.0, self._squares / self._count - mean * mean))

    def figures(self) -> dict[str, float] | None:
        """min, avg, p95 and max in seconds; None before the first duration."""
        with self._folded():
            if not self._count:
                return None
            return {
                "min": self._low,
                "avg": self._total / self._count,
                "p95": percentile(self._recent, 0.95),
                "max": self._high,
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
