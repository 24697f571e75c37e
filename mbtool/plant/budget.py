"""A serial link's line budget (issue 44): the share of the line's time the polls an inventory
asks need, worked out when it is loaded, before anything is opened.

A serial line carries one frame at a time.  Each transaction of a poll takes its request's and
its reply's characters on the line (their ADUs as the link's framer builds them, a character
the line's bits: start, data, parity, stop), the silence before the reply (t3.5: a device
answers no sooner) and the one before the next request (t3.5, or the link's --pause where that
is longer: mbtool waits both from the end of the reply).  A group read every ``interval``
seconds needs its reads' time over its interval, each second; a link's load is the sum over
its devices' groups (what is read once is left out: it is no pace).  A load above 1 is more
than the line has, and the groups cannot keep their intervals.

The device's own time to answer past t3.5 is not known before it is polled: the estimate is
what the line needs at the least.  A link that is not a serial line of mbtool's own (TCP, a
gateway) has no budget here: the gateway's bus is out of sight.  No clock, no I/O.
"""

from __future__ import annotations

import math

from mbtool.codec.framing import make_framer
from mbtool.codec.pdu import Request
from mbtool.codec.record import record
from mbtool.codec.timing import char_time, character_bits, silent_interval
from mbtool.errors import MbtoolError
from mbtool.link.connection import Connection, framer_name
from mbtool.link.transport import parse_target


@record
class Budget:
    """A serial link's load: the line's seconds a second its groups need, the reads a second
    they ask, at its baud rate."""

    link: str
    baud: int
    seconds: float  # of line time, each second: the load (1.0: the whole line)
    reads: float  # transactions a second

    def line(self) -> str:
        """The budget as one line: ``bus1: the asked polls need 0.413 s of line time a second at
        9600 baud (41.3%), 3.0 reads/s``."""
        return (
            f"{self.link}: the asked polls need {self.seconds:.3f} s of line time a second "
            f"at {self.baud} baud ({self.seconds:.1%}), {self.reads:.1f} reads/s"
        )


def serial_line(connection: Connection | None) -> bool:
    """Whether the link is a serial line of mbtool's own, whose time this module can figure (a
    target of a scheme registered in process, such as sim://, is none)."""
    if connection is None or not connection.port:
        return False
    try:
        return parse_target(connection.port).scheme == "serial"
    except MbtoolError:  # a scheme this module does not know (one of the tests' own)
        return False


def transaction_seconds(connection: Connection, unit: int, request: Request) -> float:
    """The line's time one transaction of ``request`` takes at the least: its request's and its
    reply's characters, and the two silences."""
    framer = make_framer(framer_name(connection))
    prefix = request.reply_prefix  # a read's reply length is known before it comes
    assert prefix is not None, "a poll reads: its replies' lengths are known"
    characters = len(framer.build(unit, request.encode())) + len(framer.build(unit, bytes(prefix[1])))
    line = connection.serial
    bits = character_bits(line.parity, line.bytesize, line.stopbits)
    t35 = silent_interval(line.baud, bits)
    return characters * char_time(line.baud, bits) + t35 + max(t35, connection.pause)


def link_budget(link, devices: list) -> Budget | None:
    """The load ``devices`` (plant.schedule's DeviceSpecs of ``link``, its LinkSpec) put on it;
    None when it is no serial line.  (The scheduler asks this module a read's line time: this
    module does not import it.)"""
    if not serial_line(link.connection):
        return None
    seconds = reads = 0.0
    for device in devices:
        for group in device.paced():
            if group.interval == math.inf:
                continue  # read once: no pace
            for block in group.reader.blocks:
                seconds += transaction_seconds(link.connection, device.unit, block.request) / group.interval
                reads += 1 / group.interval
    return Budget(link.name, link.connection.serial.baud, seconds, reads)


def budgets(links: dict, devices: list) -> list[Budget]:
    """Each serial link's budget, in the inventory's order."""
    found = (link_budget(link, [d for d in devices if d.link == name]) for name, link in links.items())
    return [budget for budget in found if budget is not None]
