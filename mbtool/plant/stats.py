"""A plant device's statistics: its polls, beside what became of each of their transactions
(``link.stats``, where every command counts transactions the same way)."""

from __future__ import annotations

from mbtool.link.stats import Stats


class PollStats(Stats):
    """One device's (or one link's) polls and transactions, added up as they happen."""

    def __init__(self) -> None:
        super().__init__()
        self.polls = 0
        self.failed_polls = 0

    def poll(self, ok: bool) -> None:
        self.polls += 1
        if not ok:
            self.failed_polls += 1

    def add(self, other: PollStats) -> None:
        super().add(other)
        self.polls += other.polls
        self.failed_polls += other.failed_polls

    def as_dict(self) -> dict:
        return {"polls": self.polls, "failed_polls": self.failed_polls, **super().as_dict()}
