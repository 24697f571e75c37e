"""Dumping a device: every readable address of its tables, found exactly.

A read is refused with exception 02 when any address it names does not exist
(spec §3), and the refusal does not say which.  So the holes are found the
only exact way: an address is a hole when a read of it alone is refused, or
when it is the one address left of a refused read.  The scan reads as much as
the spec allows (125 registers, 2000 bits) at first; a refused read is halved
toward its missing address (a binary search for the first one); past a hole it
asks one address at a time until one answers, and then gallops: each read that
succeeds doubles the next, up to the limit.  Galloping keeps a lone register
between holes at two requests (the second, refused, leaves the address after
it as the one in doubt: a hole, known without asking), where jumping straight
to the limit would spend a binary search on it.

A readable run of n addresses costs n / limit reads plus about 2 log2(limit)
at its edges; each hole costs at most one request, which no exact method can
beat: a refused read confirms at most one address it alone leaves in doubt.

Exception 01 to a table's reads means the device has no such table: it is
skipped, and said so.  What is shown as the scan goes is not decided here: the
CLI passes ``progress(done)`` (addresses covered so far).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any  # a reply: the class its request decodes

from mbtool.codec.data_access import (
    MAX_READ_BITS,
    MAX_READ_REGISTERS,
)
from mbtool.codec.device_id import ReadDeviceIdentification
from mbtool.codec.errors import FrameError, ModbusException
from mbtool.codec.pdu import ExceptionCode, Request
from mbtool.codec.record import record
from mbtool.codec.tables import READS, Table


@record
class Span:
    """A range of one table to dump: ``first`` to ``last``, both included."""

    table: Table
    first: int = 0
    last: int = 0xFFFF

    @property
    def size(self) -> int:
        return self.last - self.first + 1


class OutOfRequests(Exception):
    """The request budget (--max-requests) is spent: what was read so far stands."""


class TableDump:
    """What one table holds: runs of consecutive readable addresses and their values."""

    def __init__(self, table: Table) -> None:
        self.table = table
        self.runs: list[tuple[int, list]] = []  # (first address, values), in address order
        self.absent = False  # the device answered exception 01: it has no such table

    def add(self, address: int, values) -> None:
        if self.runs and self.runs[-1][0] + len(self.runs[-1][1]) == address:
            self.runs[-1][1].extend(values)
        else:
            self.runs.append((address, list(values)))

    @property
    def count(self) -> int:
        return sum(len(values) for _, values in self.runs)


class Dumper:
    """Reads spans through ``execute(request) -> reply``, counting requests against a budget."""

    def __init__(self, execute: Callable[[Request], Any], max_requests: int | None = None) -> None:
        self.execute = execute
        self.max_requests = max_requests
        self.requests = 0
        self.refused = 0  # of them, refused with exception 02 (an address missing)

    def _read(self, request: Request):
        if self.max_requests is not None and self.requests >= self.max_requests:
            raise OutOfRequests
        self.requests += 1
        return self.execute(request)

    def dump(self, span: Span, into: TableDump, progress: Callable[[int], None] | None = None) -> None:
        """Add every readable address of ``span`` to ``into``; raises OutOfRequests,
        KeyboardInterrupt or a link error with what was read so far already in ``into``."""
        table = span.table
        limit = MAX_READ_BITS if table.bits else MAX_READ_REGISTERS
        read = READS[table.name]
        address, end, size = span.first, span.last + 1, limit
        missing_before = None  # a refused read ended here: an address before it is missing
        while address < end:
            if missing_before == address + 1:  # the one address left of a refused read
                address, missing_before, size = address + 1, None, 1
                if progress is not None:
                    progress(address - span.first)
                continue
            if missing_before is None:
                count = min(size, end - address)
            else:  # halve the stretch that holds the missing address
                count = max(1, (missing_before - address) // 2)
            try:
                reply = self._read(read(address, count))
            except ModbusException as error:
                if error.exception_code == ExceptionCode.ILLEGAL_FUNCTION:
                    into.absent = True  # no such table on this device
                    return
                if error.exception_code != ExceptionCode.ILLEGAL_DATA_ADDRESS:
                    raise
                self.refused += 1
                if count > 1:
                    missing_before = address + count
                    continue
                address, missing_before, size = address + 1, None, 1  # a hole; the next may be one too
            else:
                into.add(address, reply.bits[:count] if table.bits else reply.registers)
                address += count
                if missing_before is None:
                    size = min(limit, count * 2)  # nothing known missing ahead: gallop
            if progress is not None:
                progress(address - span.first)


def read_identification(execute: Callable[[Request], Any], read_code: int) -> tuple[dict[int, bytes], int]:
    """Every object of a level of FC 43/14 (spec §3), following more-follows across
    requests; and the device's conformity level (codec.device_id.conformity_name names it).  A more-follows that points back at an
    object already asked for is a bad reply (FrameError), not a loop."""

    objects: dict[int, bytes] = {}
    next_id, asked = 0, set()
    while True:
        asked.add(next_id)
        reply = execute(ReadDeviceIdentification(read_code, next_id))
        objects.update(reply.objects)
        if not reply.more_follows:
            return objects, reply.conformity
        next_id = reply.next_object_id
        if next_id in asked:
            raise FrameError(f"more-follows points back to object 0x{next_id:02X}, already asked for")


def runs_of(addresses) -> list[tuple[int, int]]:
    """(first, last) of each run of consecutive addresses, from sorted addresses."""
    runs: list[list[int]] = []
    for address in addresses:
        if runs and runs[-1][1] == address - 1:
            runs[-1][1] = address
        else:
            runs.append([address, address])
    return [(first, last) for first, last in runs]
