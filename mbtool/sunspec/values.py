"""A model's points as read: each value by the register map's own rules (``registermap``),
so that ``mbtool sunspec`` shows what ``read -m`` of the map it writes reads.

A point's value has its scale factor applied (raw × 10^sf, the sf read with it); a raw
value SunSpec calls unimplemented (0xFFFF, 0x8000, 0x80000000, NaN, a string of NULs, 0
for an accumulator: as the point's type says) is no value, and so is a value whose scale
factor is unimplemented.  An enum's value is its symbol; a bitfield's set bits are named.
"""

from __future__ import annotations

from mbtool.codec.record import record
from mbtool.codec.values import decode_values
from mbtool.registermap.load import RegisterMap, build_map
from mbtool.sunspec.layout import Layout, Slot, address_text, bits_set, map_rows


@record
class PointValue:
    slot: Slot
    raw: tuple[int, ...]  # its registers
    value: object  # in its units (its symbol for an enum); None: no value
    implemented: bool  # its raw value is not the one SunSpec calls unimplemented
    factor: int | None = None  # the scale factor applied (its exponent); None: none or none read
    bits: tuple[str, ...] = ()  # a bitfield's set bits


def model_map(layout: Layout) -> RegisterMap | None:
    """The register map of a model's points (None when it has none a map carries)."""
    rows, _ = map_rows(layout)
    return build_map(layout.title, {}, rows) if rows else None


def read_values(layout: Layout, registers: tuple[int, ...] | list[int]) -> dict[str, PointValue]:
    """Each point of the model by its name in the map, as its registers read."""
    if layout.root is None:
        return {}
    register_map = model_map(layout)
    points = register_map.points if register_map is not None else {}

    def raw_of(address: int, size: int) -> tuple[int, ...]:
        return tuple(registers[address - layout.start : address - layout.start + size])

    out = {}
    for slot in layout.root.every_slot():
        raw = raw_of(slot.address, slot.size)
        point = points.get(slot.name)
        if point is None:  # no map type carries it: an address, shown as pysunspec2 writes it
            text = address_text(list(raw))
            out[slot.name] = PointValue(slot, raw, text, text is not None)
            continue
        held = decode_values(list(raw), point.type)[0]
        factor = slot.factor if isinstance(slot.factor, int) else None
        if point.scale_ref is not None:
            scale = point.scale_ref
            read = scale.value_of(list(raw_of(scale.address, scale.size)))
            factor = read if isinstance(read, int) else None  # a sunssf is an int16, or no value
        value = point.value_of(list(raw), factor)
        bits: tuple[str, ...] = ()
        if slot.point["type"].startswith("bitfield") and isinstance(value, int):  # None: no value
            bits = tuple(bits_set(slot, value))
        out[slot.name] = PointValue(slot, raw, value, not point.is_invalid(held), factor, bits)
    return out
