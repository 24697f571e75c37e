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

    def add(self, other: Stats, recent: bool = True) -> None:
        super().add(other, recent)
        if isinstance(other, PollStats):
            self.polls += other.polls
            self.failed_polls += other.failed_polls

    def as_dict(self) -> dict:
        return {"polls": self.polls, "failed_polls": self.failed_polls, **super().as_dict()}


class DeviceAndLink:
    """Where the managed link counts a plant's transaction: in its device's statistics and in its
    link's at once, so that a link's totals are kept as transactions end rather than added up
    again from every device of the link after each poll (the exporter shows them after each)."""

    __slots__ = ("device", "link")

    def __init__(self, device: Stats, link: Stats) -> None:
        self.device = device
        self.link = link

    def answered(self, attempts: int, rtt: float | None) -> None:
        self.device.answered(attempts, rtt)
        self.link.answered(attempts, rtt)

    def transaction(self, error: BaseException | None, attempts: int, rtt: float | None = None) -> str:
        self.link.transaction(error, attempts, rtt)
        return self.device.transaction(error, attempts, rtt)
