"""What became of each transaction: the counts that tell a wiring fault (corrupt frames) from a
wrong address or a sleeping device (timeouts) and from a slow one (the round-trip time).

Every transaction the master makes ends as exactly one of: answered, an exception (by its
code), a timeout (nothing came), corrupt (a CRC/LRC or framing error: the wire), not ours (an
intact frame for another unit or transaction id), the link lost (the peer hung up, the port
went away, before or during the reply: exit 3) or no connection (the link could not be opened,
reached or written: refused, port unreachable, a TLS handshake that failed, no such serial
port: exit 6).  The kind follows the exit code, so a failure is one kind wherever it is shown:
the summaries, ping's lines, the exporter's ``modbus_error_info{kind}``.  An answer that came on a retry is also counted as a retry that
recovered.  A reply's round trip is in the figures when its arrival is known, else the reply
is counted as untimed (the client's ``rtt``).  Every command counts the same way: the managed link
(``link.managed``, which polling, the plant, ping, scan, the bridge and the exporter's scrape
take their links from) counts each transaction it carries in the ``Stats`` it is given, the
one place a transaction is counted; none judges outcomes of its own.
"""

from __future__ import annotations

from collections import Counter
from typing import Self

from mbtool.codec.errors import (
    ChecksumError,
    FrameError,
    MismatchError,
    ModbusException,
    exceptions_by_code,
    exceptions_text,
)
from mbtool.durations import Durations
from mbtool.errors import NoResponse
from mbtool.link.transport import ConnectionClosed

OUTCOMES = ("answered", "exception", "timeout", "corrupt", "not_ours", "link_lost", "connection")


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
    if isinstance(error, ConnectionClosed):
        return "link_lost"
    if isinstance(error, NoResponse):
        return "timeout"
    # Cannot open, reach or write the link: ConnectionFailed, or the OSError it stands for
    # (link_failure), exit 6.
    return "connection"


class Stats:
    """The transactions with one device (or over one link), added up as they end."""

    def __init__(self) -> None:
        # outcome -> the transactions that ended so; a plain dict with every outcome in it, as
        # a poll's every transaction adds one (a Counter's update costs several times more)
        self.outcomes: dict[str, int] = dict.fromkeys(OUTCOMES, 0)
        self.exceptions: Counter[int] = Counter()  # exception code -> count
        self.recovered = 0  # answers that came on a retry
        self.rtt = Durations()  # request to reply, for every reply (exceptions too) timed
        self.untimed = 0  # replies whose round trip is not known (Client.rtt), left out of rtt

    @property
    def transactions(self) -> int:
        """Every transaction that ended, whatever its outcome."""
        return sum(self.outcomes.values())

    def answered(self, attempts: int, rtt: float | None) -> None:
        """A transaction answered (transaction(None, ...)'s outcome, counted the short way: a
        poll's every transaction)."""
        self.outcomes["answered"] += 1
        if attempts > 1:
            self.recovered += 1
        if rtt is not None:
            self.rtt.add(rtt)
        else:
            self.untimed += 1

    def transaction(self, error: BaseException | None, attempts: int, rtt: float | None = None) -> str:
        """A transaction ended: ``error`` is what it raised (None: answered), after ``attempts``
        requests on the wire, ``rtt`` seconds from the request to its reply if one came and its
        arrival is known.  Its outcome, one of OUTCOMES."""
        outcome = outcome_of(error)
        self.outcomes[outcome] += 1
        if isinstance(error, ModbusException):  # the outcome "exception"
            self.exceptions[error.exception_code] += 1
        elif outcome == "answered" and attempts > 1:
            self.recovered += 1
        if outcome in ("answered", "exception"):  # a reply's; not that of an attempt before a failure
            if rtt is not None:
                self.rtt.add(rtt)
            else:
                self.untimed += 1
        return outcome

    def add(self, other: Stats, recent: bool = True) -> None:
        """Fold another's counts into these (a link's are its devices'); ``recent=False``
        leaves out the window of recent round trips (Durations.merge)."""
        for outcome, count in other.outcomes.items():
            self.outcomes[outcome] += count
        self.exceptions.update(other.exceptions)
        self.recovered += other.recovered
        self.untimed += other.untimed
        self.rtt.merge(other.rtt, recent)

    def copy(self) -> Self:
        """These counts as they are now, of the same kind (a plant's PollStats with its polls),
        for a record a link's thread publishes: the reader gets its own, which no later
        transaction changes.  Made whole, not added to empty counts."""
        copy = object.__new__(self.__class__)
        copy.__dict__.update(self.__dict__)  # the numbers; what changes in place is copied next
        copy.outcomes = dict(self.outcomes)
        copy.exceptions = self.exceptions.copy()
        copy.rtt = self.rtt.copy()
        return copy

    def rtt_figures(self) -> dict[str, float] | None:
        """min, avg, p95 and max round-trip time in seconds; None before the first answer."""
        return self.rtt.figures()

    def exceptions_text(self) -> str:
        """The exceptions by code, "02:3,0B:1"; "0" when none came."""
        return exceptions_text(self.exceptions)

    def as_dict(self) -> dict:
        return {
            "transactions": self.transactions,
            **{outcome: self.outcomes[outcome] for outcome in OUTCOMES},
            "exceptions_by_code": exceptions_by_code(self.exceptions),
            "retries_recovered": self.recovered,
            "rtt_seconds": self.rtt_figures(),
            # The histogram: how many round trips took at most each bound (cumulative, as
            # Prometheus's buckets), the last bound +Inf (null in JSON).
            "rtt_buckets": [[bound, count] for bound, count in self.rtt.buckets()],
            "rtt_untimed": self.untimed,  # replies left out of the figures: arrival not known
        }

    def outcomes_text(self) -> str:
        """Every outcome and the retries that recovered, for a summary line."""
        counts = ", ".join(
            f"{outcome.replace('_', ' ')} {self.outcomes[outcome]}"
            + (f" ({self.exceptions_text()})" if outcome == "exception" and self.exceptions else "")
            for outcome in OUTCOMES
        )
        return f"transactions {self.transactions}: {counts}; retries recovered {self.recovered}"

    def rtt_text(self, names: tuple[str, ...] = ("min", "avg", "p95", "max")) -> str:
        """The round trips' figures (Durations.text), and how many replies they leave out."""
        return self.rtt.text(names) + untimed_text(self.untimed)

    def __str__(self) -> str:
        """One line for a summary: every outcome, the retries that recovered and the rtt."""
        return f"{self.outcomes_text()}; rtt {self.rtt_text()}"


def untimed_text(untimed: int) -> str:
    """Beside round-trip figures: " (3 untimed)", the replies they leave out; "" when none."""
    return f" ({untimed} untimed)" if untimed else ""
