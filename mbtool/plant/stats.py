"""What became of each transaction on a link, per device: the counts that tell a wiring
fault (corrupt frames) from a wrong address or a sleeping device (timeouts) and from a
slow one (the round-trip time).

Every transaction ends as exactly one of: answered, an exception (by its code), a timeout
(nothing came), corrupt (a CRC/LRC or framing error: the wire), not ours (an intact frame
for another unit or transaction), or the link failing (it closed, or could not be
written: link_lost).  An answer that came on a retry is also counted as a retry that recovered.
"""

from __future__ import annotations

import math
from bisect import bisect_left
from collections import Counter, deque

from mbtool.codec.errors import ChecksumError, FrameError, MismatchError, ModbusException
from mbtool.errors import NoResponse
from mbtool.link.transport import ConnectionClosed

# Round-trip times kept for the 95th percentile: the most recent, so a run left going for
# weeks keeps a bounded window and a percentile of the device as it is now.
RTT_WINDOW = 1000

# The round-trip histogram's upper bounds in seconds, one list for every count of it: each
# bucket holds the round trips up to its bound (Prometheus's "le"), one more those past the
# last.  1 ms is a loopback TCP device, 10 s a slow gateway behind a 1200-baud line.
RTT_BUCKETS = (0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0)

OUTCOMES = ("answered", "exception", "timeout", "corrupt", "not_ours", "link_lost")


def outcome_of(error: BaseException | None) -> str:
    """The one outcome a transaction ended in, from what Client.execute raised (None: a reply).

    The client raises the most telling failure of its attempts: bytes that came (a bad CRC,
    a reply for another unit) beat a later silence."""
    if error is None:
        return "answered"
    if isinstance(error, ModbusException):
        return "exception"
    if isinstance(error, MismatchError):
        return "not_ours"
    if isinstance(error, ChecksumError | FrameError):
        return "corrupt"
    if isinstance(error, NoResponse) and not isinstance(error, ConnectionClosed):
        return "timeout"
    return "link_lost"


class Stats:
    """One device's (or one link's) transactions and polls, added up as they happen."""

    def __init__(self) -> None:
        self.polls = 0
        self.failed_polls = 0
        self.transactions = 0
        self.outcomes: Counter[str] = Counter()
        self.exceptions: Counter[int] = Counter()  # exception code -> count
        self.recovered = 0  # answers that came on a retry
        self.rtt: deque[float] = deque(maxlen=RTT_WINDOW)
        self.rtt_count = 0
        self.rtt_total = 0.0
        self.rtt_min = math.inf
        self.rtt_max = 0.0
        self.rtt_buckets = [0] * (len(RTT_BUCKETS) + 1)  # per bucket, not cumulative

    def transaction(self, error: BaseException | None, attempts: int) -> None:
        """A transaction ended: ``error`` is what it raised (None: answered), after ``attempts``
        requests on the wire."""
        self.transactions += 1
        outcome = outcome_of(error)
        self.outcomes[outcome] += 1
        if outcome == "exception":
            self.exceptions[error.exception_code] += 1
        elif outcome == "answered" and attempts > 1:
            self.recovered += 1

    def round_trip(self, seconds: float) -> None:
        self.rtt.append(seconds)
        self.rtt_count += 1
        self.rtt_total += seconds
        self.rtt_min = min(self.rtt_min, seconds)
        self.rtt_max = max(self.rtt_max, seconds)
        self.rtt_buckets[bisect_left(RTT_BUCKETS, seconds)] += 1

    def poll(self, ok: bool) -> None:
        self.polls += 1
        if not ok:
            self.failed_polls += 1

    def add(self, other: Stats) -> None:
        """Fold another's counts into these (a link's are its devices')."""
        self.polls += other.polls
        self.failed_polls += other.failed_polls
        self.transactions += other.transactions
        self.outcomes.update(other.outcomes)
        self.exceptions.update(other.exceptions)
        self.recovered += other.recovered
        self.rtt.extend(other.rtt)
        self.rtt_count += other.rtt_count
        self.rtt_total += other.rtt_total
        self.rtt_min = min(self.rtt_min, other.rtt_min)
        self.rtt_max = max(self.rtt_max, other.rtt_max)
        self.rtt_buckets = [
            mine + theirs for mine, theirs in zip(self.rtt_buckets, other.rtt_buckets, strict=True)
        ]

    def rtt_histogram(self) -> list[tuple[float, int]]:
        """(upper bound, round trips that took at most that long), cumulative, the last bound
        infinity: a Prometheus histogram's buckets."""
        running, out = 0, []
        for bound, count in zip((*RTT_BUCKETS, math.inf), self.rtt_buckets, strict=True):
            running += count
            out.append((bound, running))
        return out

    def rtt_figures(self) -> dict[str, float] | None:
        """min, avg, p95 and max round-trip time in seconds; None before the first answer."""
        if not self.rtt_count:
            return None
        ordered = sorted(self.rtt)
        p95 = ordered[min(len(ordered) - 1, math.ceil(0.95 * len(ordered)) - 1)]
        return {
            "min": self.rtt_min,
            "avg": self.rtt_total / self.rtt_count,
            "p95": p95,
            "max": self.rtt_max,
        }

    def as_dict(self) -> dict:
        return {
            "polls": self.polls,
            "failed_polls": self.failed_polls,
            "transactions": self.transactions,
            **{outcome: self.outcomes[outcome] for outcome in OUTCOMES},
            "exceptions_by_code": {f"{code:02X}": n for code, n in sorted(self.exceptions.items())},
            "retries_recovered": self.recovered,
            "rtt_seconds": self.rtt_figures(),
        }
