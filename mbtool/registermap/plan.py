"""Reading and writing a map's points in as few requests as the spec allows.

Points of one table that lie close together are read by one request: a block
grows while it stays within the spec's limit for one read (125 registers,
2000 bits; spec §3) and while the registers it reads that no point uses, in
any one gap, are at most the map's ``max_gap``.  Growing each block as far as
it goes, from the lowest address up, gives the fewest requests: any plan's
first block ends no later than the greedy one's, and so on for every block.

A point and its scale factor (``scale_ref``, SunSpec's W and W_SF) are read in one
request, over any gap, when the two fit in one: read apart, the device may change the
scale factor in between and the value is off by a power of ten (the SunSpec
specification asks a client to read a point and its scale factor together).  A scale
factor is read with its point even when it was not asked for.

A device that answers a merged read with exception 02 (it lacks an address in
a gap, or one point's address) is asked again point by point, and the split is
kept for the reads after (``MapReader``, polling).  A point the device refuses
on its own is not read and the others still are: the read is partial
(``PartialRead``, exit 8), each failure naming its point.  This is the one rule
for ``read -m``, polling, ``check -m`` and the monitoring outputs.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Any

from mbtool.codec.data_access import (
    MAX_READ_BITS,
    MAX_READ_REGISTERS,
    MaskWriteRegister,
)
from mbtool.codec.errors import ModbusException
from mbtool.codec.pdu import ExceptionCode, Request
from mbtool.codec.record import field, record
from mbtool.codec.tables import READS, Table, write_of
from mbtool.errors import PartialRead, UsageError
from mbtool.registermap.point import Point, PointValue


@record
class Block:
    """One read request and the points it serves.  The request, and where each point lies
    in its reply, are worked out with the block: a map polled reads the same blocks, with the
    same requests, poll after poll."""

    table: Table
    address: int
    count: int
    points: tuple[Point, ...]
    request: Request = field(default=None, compare=False)  # made from the fields above
    spans: tuple = field(default=(), compare=False)  # (point, first, end) in the reply's data

    def __post_init__(self) -> None:
        object.__setattr__(self, "request", READS[self.table.name](self.address, self.count))
        first = self.address
        spans = tuple((point, point.address - first, point.end - first) for point in self.points)
        object.__setattr__(self, "spans", spans)


@record
class Reading:
    """A point's value as read, with the raw registers (or bit) it came from; or, for a point
    the device refused, no value and the device's answer."""

    point: Point
    value: PointValue
    raw: tuple
    error: PointException | None = None

    def __init__(
        self, point: Point, value: PointValue, raw: tuple, error: PointException | None = None
    ) -> None:
        # By hand: one a point a poll (codec/record.py).
        fields = self.__dict__
        fields["point"] = point
        fields["value"] = value
        fields["raw"] = raw
        fields["error"] = error


def plan_reads(points: Iterable[Point], max_gap: int = 0) -> list[Block]:
    by_table: dict[str, list[Point]] = {}
    for point in points:
        by_table.setdefault(point.table.name, []).append(point)
    blocks = []
    for table_points in by_table.values():
        table_points.sort(key=lambda p: (p.address, p.end))
        table = table_points[0].table
        limit = MAX_READ_BITS if table.bits else MAX_READ_REGISTERS
        partners = _partners(table_points)
        members: list[Point] = []
        start = end = reach = 0
        for point in table_points:
            # reach: where a member's scale factor (or a point it scales) ends, when one read
            # from this block's start can get there.
            joins = point.address - end <= max_gap or point.address < reach
            if members and joins and max(end, point.end) - start <= limit:
                members.append(point)
                end = max(end, point.end)
            else:
                if members:
                    blocks.append(Block(table, start, end - start, tuple(members)))
                members, start, end, reach = [point], point.address, point.end, 0
            for partner in partners.get(point.name, ()):
                if partner.end - start <= limit:
                    reach = max(reach, partner.end)
        blocks.append(Block(table, start, end - start, tuple(members)))
    return blocks


def _partners(points: list[Point]) -> dict[str, list[Point]]:
    """Each point's scale factor and the points it scales, among ``points`` (one table's)."""
    names = {point.name for point in points}
    out: dict[str, list[Point]] = {}
    for point in points:
        factor = point.scale_ref
        if factor is not None and factor.name in names:
            out.setdefault(point.name, []).append(factor)
            out.setdefault(factor.name, []).append(point)
    return out


def with_scale_factors(points: Iterable[Point]) -> list[Point]:
    """The points and the scale factors they need that are not among them."""
    points = list(points)
    names = {point.name for point in points}
    for point in list(points):
        factor = point.scale_ref
        if factor is not None and factor.name not in names:
            names.add(factor.name)
            points.append(factor)
    return points


# Any: the reply is the class its request decodes (a read's BitsResponse or RegistersResponse).
Execute = Callable[[Request], Any]


class MapReader:
    """The reads that serve a map's points, kept from one read (one poll) to the next."""

    request = None  # a poll is its reads, not one request (plant.schedule.Reader)

    def __init__(self, points: Iterable[Point], max_gap: int = 0) -> None:
        self.points = list(points)
        self.blocks = plan_reads(with_scale_factors(self.points), max_gap)

    def read(self, execute: Execute) -> list[Reading]:
        """Every point's reading, in the order the points were given.

        A merged read refused with exception 02 is split into its points' own reads, for
        good: the next read starts from the split.  An exception to a point's own read (or
        to a read of points that cannot be split further) is that point's failure: the
        others are still read, and PartialRead carries them all.  When no point could be
        read, the first failure is the error.  A link failure (no response, a bad reply)
        ends the read: the device cannot be read at all."""
        readings: dict[str, Reading] = {}
        blocks = []
        for block in self.blocks:
            try:
                readings |= _read_block(execute, block)
                blocks.append(block)
            except ModbusException as error:
                if error.exception_code != ExceptionCode.ILLEGAL_DATA_ADDRESS or len(block.points) == 1:
                    readings |= _refused(block, error)
                    blocks.append(block)
                    continue
                for point in block.points:  # which point is it?
                    single = Block(point.table, point.address, point.size, (point,))
                    blocks.append(single)
                    try:
                        readings |= _read_block(execute, single)
                    except ModbusException as failure:
                        readings |= _refused(single, failure)
        self.blocks = blocks
        ordered = [_scaled(readings, readings[point.name]) for point in self.points]
        failures = [reading.error for reading in ordered if reading.error is not None]
        if len(failures) == len(ordered):
            raise failures[0]
        if failures:
            raise PartialRead(ordered, failures)
        return ordered


def read_points(execute: Execute, points: list[Point], max_gap: int = 0) -> list[Reading]:
    """Every point's reading, in one read (MapReader.read's rule)."""
    return MapReader(points, max_gap).read(execute)


def _scaled(readings: dict[str, Reading], reading: Reading) -> Reading:
    """A point's reading with its scale factor applied, the factor read in the same read;
    a factor the device refused leaves the point unread too, with the device's answer."""
    factor = reading.point.scale_ref
    if factor is None or reading.error is not None:
        return reading
    scale = readings[factor.name]
    if scale.error is not None:
        return Reading(reading.point, None, (), PointException(reading.point, scale.error, factor))
    sf = scale.value if isinstance(scale.value, int) else None  # a scale factor is an integer, or no value
    value = reading.point.value_of(reading.raw, sf)
    return Reading(reading.point, value, reading.raw)


def _refused(block: Block, error: ModbusException) -> dict[str, Reading]:
    return {point.name: Reading(point, None, (), PointException(point, error)) for point in block.points}


def _read_block(execute: Execute, block: Block) -> dict[str, Reading]:
    reply = execute(block.request)
    data = reply.bits if block.table.bits else reply.registers
    out = {}
    for point, first, end in block.spans:
        raw = data[first:end]
        # A point with a scale_ref is worked out once its factor is read too (_scaled).
        value = point.value_of(raw) if point.scale_ref is None else None
        out[point.name] = Reading(point, value, raw)
    return out


class PointException(ModbusException):
    """An exception reply to a point's own read (or to its scale factor's, ``factor``): the
    message names the point."""

    def __init__(self, point: Point, error: ModbusException, factor: Point | None = None) -> None:
        super().__init__(error.function_code, error.exception_code)
        answer = getattr(error, "answer", str(error))
        if factor is not None:
            answer = f"its scale factor {factor.named}: {answer}"
        self.answer = answer  # the device's answer alone, where the point is named apart
        self.args = (f"{point.named}: {answer}",)


def write_request(
    point: Point, text: str, multiple: bool = False, nonfinite: bool = False, scale_factor: int | None = None
) -> Request:
    """The request that writes ``text`` to a point: FC05/06 for one item, FC15/16 for more
    or when ``multiple`` (some devices accept only FC15/16); bits of a register: see ``bit_request``.
    ``nonfinite``: a float point may be written nan or inf.  ``scale_factor``: what the
    point's ``scale_ref`` reads now (without it, point.NoScaleFactor once the rest is checked)."""
    if not point.writable:
        why = (
            f"{point.table.items} are read-only"
            if not point.table.writable
            else "the map does not mark it rw"
        )
        raise UsageError(f"{point.name} ({point.ref}) is not writable: {why}")
    raw = point.raw_for(text, nonfinite, scale_factor)
    if point.bit is not None:
        return bit_request(point.address, point.bit, bool(raw))
    values = [raw] if point.table.bits else point.registers_of(raw)
    return write_of(point.table, point.address, values, multiple)


def bit_request(address: int, bit: int, on: bool) -> MaskWriteRegister:
    """FC22 that sets or clears one bit and leaves the others (spec §3: AND mask keeps,
    OR mask sets where the AND mask is 0)."""
    mask = 1 << bit
    return MaskWriteRegister(address, 0xFFFF ^ mask, mask if on else 0)


def with_bit(current: int, bit: int, on: bool) -> int:
    """A register's value with one bit set or cleared: --rmw's modify step."""
    return current | 1 << bit if on else current & ~(1 << bit) & 0xFFFF
