"""A managed link: the one place a master's link is opened, opened again when it is lost, backed
off, handed its --pause, and judged lost or not.

Every command that keeps a link across transactions (polling, the plant, ping, scan, the
bridge, the exporter's scrape) takes its link from a ``ManagedLink`` and calls its
``execute(unit, request)``; none opens, reopens or backs off by hand.

The one back-off rule (``Backoff``): after a link fails -- it could not be opened, or it was
lost (``link_lost``) -- it is opened again no sooner than ``first`` seconds after the last open
began, and each open that fails in a row doubles that wait, up to ``longest``.  An open that
succeeds starts the count again.  So a device that is restarting or unplugged is not hammered
(``--interval 0`` makes a log line a wait, not thousands), and a dead link of a plant costs one
try a back-off.  A link closed on purpose (--reconnect-each) is opened again at once.

The link's clock (``clock``: ``monotonic`` and ``sleep``, the time module unless a test gives
its own) is the only one it reads; the client keeps its own for its deadlines.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from contextlib import AbstractContextManager, ExitStack
from typing import TYPE_CHECKING

from mbtool.errors import KNOWN_ERRORS, ConnectionFailed, link_failure
from mbtool.link.connection import close_quietly
from mbtool.link.transport import ConnectionClosed

if TYPE_CHECKING:
    from mbtool.link.client import Client

# What says the link itself is gone (a device restarted, a cable pulled, a peer that closed the
# connection): an OSError from the system, or the master's own word for it.  A timeout, a bad
# frame or an exception is the device's or the wire's, on a link still there.
LOST = (OSError, ConnectionFailed, ConnectionClosed)


def link_lost(error: BaseException) -> bool:
    """Whether ``error`` means the link is gone and must be opened anew: the one judgement."""
    return isinstance(error, LOST)


class Backoff:
    """How long a failed link waits before it is opened again: ``first`` seconds, doubled with
    each failure in a row, up to ``longest`` (``first`` when not given)."""

    def __init__(self, first: float, longest: float | None = None) -> None:
        self.first = first
        self.longest = first if longest is None else longest
        self.wait = 0.0  # the wait after the last failure; 0 while the link is well

    def failed(self) -> float:
        """One more failure in a row: the wait before the next open."""
        self.wait = min(2 * self.wait if self.wait else self.first, self.longest)
        return self.wait

    def reset(self) -> None:
        self.wait = 0.0


class ManagedLink:
    """One link to a device or a bus, opened by ``open_link()`` (a context manager giving an
    open Client, as ``link.connection.open_client`` does) when a transaction needs it.

    ``stats``: where ``execute`` counts each transaction (``link.stats.Stats``, or anything
    with its ``answered`` and ``transaction``), None: not counted.  A caller may change it
    between transactions (a plant counts each device's apart)."""

    def __init__(
        self,
        open_link: Callable[[], AbstractContextManager],
        backoff: Backoff,
        stats=None,
        clock=time,
    ) -> None:
        self.open_link = open_link
        self.backoff = backoff
        self.stats = stats
        self.clock = clock
        self.client: Client | None = None  # the open Client; None while closed
        self.last: Client | None = None  # the Client of the last transaction (its attempts and rtt)
        self._link = ExitStack()
        self.opened_at = -math.inf  # monotonic: when the last open began
        self.ready_at = -math.inf  # monotonic: not opened again before
        # When the last link's last transaction ended, on the client's clock: a new link to the
        # same device still keeps --pause after it (a lost link, --reconnect-each).
        self.ended_at = -math.inf
        self.opens = 0  # links opened
        self.failures = 0  # opens that failed

    # -- what a caller asks ----------------------------------------------------------

    @property
    def attempts(self) -> int:
        """The requests the last transaction sent (1, or more when it retried)."""
        return self.last.attempts if self.last is not None else 0

    @property
    def rtt(self) -> float | None:
        """The last transaction's round trip; None when no reply came."""
        return self.last.rtt if self.last is not None else None

    def wait(self) -> None:
        """Sleep until the link may be opened again (at once when it is open, or well)."""
        if self.client is None:
            delay = self.ready_at - self.clock.monotonic()
            if delay > 0:
                self.clock.sleep(delay)

    def open(self):
        """The open Client: the one open, else a new one.  A link that cannot be opened
        raises what opening it raised (an OSError as the ConnectionFailed it means, exit 6), and
        counts as a failure of the back-off rule; it is not waited for here (``wait``)."""
        if self.client is not None:
            return self.client
        self.opened_at = self.clock.monotonic()
        link = ExitStack()
        try:
            client = link.enter_context(self.open_link())
        except (*KNOWN_ERRORS, OSError) as error:
            close_quietly(link)
            self.failures += 1
            self.ready_at = self.opened_at + self.backoff.failed()
            failure = link_failure(error)
            if failure is error:
                raise
            raise failure from None
        self._link, self.client, self.last = link, client, client
        client.ended_at = self.ended_at  # the device still wants its pause after that
        self.opens += 1
        self.backoff.reset()
        return client

    def execute(self, unit: int, request):
        """One transaction on the link, opened first if it is not; counted in ``stats``.  A
        lost link is closed (and backed off) before its error is raised: the next transaction
        opens a new one."""
        client = self.client or self.open()
        try:
            reply = client.execute(unit, request)
        except Exception as error:
            if self.stats is not None:
                self.stats.transaction(error, client.attempts, client.rtt)
            if isinstance(error, LOST):
                self.drop()
            raise
        if reply is not None and self.stats is not None:
            self.stats.answered(client.attempts, client.rtt)
        return reply

    def drop(self, on_purpose: bool = False) -> None:
        """Close the link.  Not ``on_purpose``: it was lost, and waits out its back-off
        before it is opened again; on purpose (--reconnect-each), it is opened again at once."""
        client = self.client
        if client is not None:
            self.ended_at = client.ended_at
            self.client = None
            close_quietly(self._link)
            self._link = ExitStack()
        # A lost link waits the first back-off from its open (a link that opens and is lost at
        # once is not hammered); one that served a while is opened again at once.
        self.ready_at = -math.inf if on_purpose else self.opened_at + self.backoff.first

    def close(self) -> None:
        """Close the link for good (the run is over): nothing left to report of it."""
        if self.client is not None:
            self.ended_at = self.client.ended_at
            self.client = None
        close_quietly(self._link)
        self._link = ExitStack()
