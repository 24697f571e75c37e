"""A model's definition laid over its registers: where each point is, what it is named in a
register map, and the map's rows that read it.

A model on the wire is its id, its length L, then L registers.  The definition gives the
points in order; a group of points may repeat: a fixed number of times, as many times as
a point of the model says (model 705's NCrv curves), or, with count 0, as many times as
the model's length holds (model 160's MPPT modules).  The length on the wire wins over
the definition wherever they disagree, and each disagreement is a warning naming the
model:

* a model shorter than its definition: the points past its end are left out (model 1's
  65 registers, the common model before its Pad was added, is a known form: no warning);
* a model longer than its definition: the registers past it are shown raw;
* a repeating group that does not fit: as many as fit, the rest of the registers raw
  (a battery whose model 803 has 6 registers where a string takes 32);
* a model id SunSpec does not define: its registers raw, and the walk goes on.
"""

from __future__ import annotations

from mbtool.codec.data_access import MAX_READ_REGISTERS
from mbtool.codec.record import field, record
from mbtool.sunspec.models import TYPES, definition, point_size
from mbtool.words import counted


@record
class Slot:
    """One point of a model, where the device holds it."""

    name: str  # its name in a map: the model's key, its groups and the point ("mppt.module1.DCA")
    point: dict = field(compare=False)  # the definition's point
    address: int  # 0-based holding register
    size: int
    factor: str | int | None = None  # the map name of its scale factor's point, or a constant exponent


@record
class Group:
    """A group of a model: its points, then its groups (a repeating one, one a repeat)."""

    name: str
    index: int | None  # 1, 2... for a repeat of a repeating group; None for a group that is one
    slots: tuple[Slot, ...]
    groups: tuple[Group, ...]

    def every_slot(self):
        yield from self.slots
        for group in self.groups:
            yield from group.every_slot()


@record
class Layout:
    model_id: int
    key: str  # the model's name in its points' names ("inverter_three_phase", "ac_meter_abcn_2")
    address: int  # where its id is (0-based)
    length: int  # L: the registers after the id and the length
    name: str  # the definition's ("" for a model SunSpec does not define)
    label: str
    root: Group | None  # None for a model SunSpec does not define
    raw: tuple[int, int] | None  # (address, count) of registers no point explains
    warnings: tuple[str, ...]

    @property
    def start(self) -> int:
        """The first register after the id and the length."""
        return self.address + 2

    @property
    def title(self) -> str:
        return f"model {self.model_id}" + (f" ({self.name})" if self.name else "")


def _are(count: int) -> str:
    return "is" if count == 1 else "are"


def lay_out(model_id: int, key: str, address: int, registers: list[int] | tuple[int, ...]) -> Layout:
    """The model whose id is at ``address``, its ``registers`` those after the length."""
    definition_group = definition(model_id)
    length = len(registers)
    where = f"model {model_id} at {address}"
    if definition_group is None:
        return Layout(
            model_id,
            key,
            address,
            length,
            "",
            "",
            None,
            (address + 2, length) if length else None,
            (
                f"{where}: SunSpec defines no model {model_id}: its {counted(length, 'register')} {_are(length)} shown raw",
            ),
        )
    laying = _Laying(model_id, key, address, registers)
    root, end = laying.group(definition_group, key, address, None, top=True)
    title = f"{where} ({definition_group['name']})"
    warnings = laying.warnings
    raw = None
    if end < laying.end:
        raw = (end, laying.end - end)
        if not laying.leftover:
            warnings.append(
                f"{title}: {counted(length, 'register')} on the wire, {end - address - 2} in its definition; "
                f"the length on the wire is used: the {counted(laying.end - end, 'register')} past the "
                f"definition {_are(laying.end - end)} shown raw"
            )
    if laying.cut and not (model_id == 1 and length == 65 and laying.cut == ["Pad"]):
        warnings.append(
            f"{title}: {counted(length, 'register')} on the wire, {end - address - 2} in its definition; "
            f"the length on the wire is used: {', '.join(laying.cut)} past its end left out"
        )
    return Layout(
        model_id,
        key,
        address,
        length,
        definition_group["name"],
        definition_group.get("label", ""),
        root,
        raw,
        tuple(warnings),
    )


class _Laying:
    """One model being laid out: the registers it has, and what it found wrong."""

    def __init__(self, model_id: int, key: str, address: int, registers) -> None:
        self.model_id = model_id
        self.key = key
        self.start = address + 2
        self.end = self.start + len(registers)
        self.registers = registers
        self.warnings: list[str] = []
        self.cut: list[str] = []  # points past the model's end
        self.leftover = False  # registers after a repeating group that do not make another
        self.top: dict[str, int] = {}  # the model's top-level points: name -> address

    def group(self, gdef: dict, prefix: str, address: int, index: int | None, top: bool = False):
        """The group at ``address`` and where the next thing starts."""
        own = {point["name"] for point in gdef.get("points", ())}
        slots = []
        for point in gdef.get("points", ()):
            size = point_size(point)
            name = point["name"]
            if top:
                self.top[name] = address
            if address + size > self.end:
                self.cut.append(f"{prefix}.{name}".removeprefix(f"{self.key}."))
            elif not (top and name in ("ID", "L")) and point["type"] != "pad":
                # The id and length are the chain's; a pad holds nothing.
                slots.append(Slot(f"{prefix}.{name}", point, address, size, self._factor(point, prefix, own)))
            address += size
        groups = []
        for sub in gdef.get("groups", ()):
            count = self._count(sub, prefix, address)
            for number in range(count):
                at = None if sub.get("count") is None else number + 1
                name = f"{prefix}.{sub['name']}{'' if at is None else at}"
                group, address = self.group(sub, name, address, at)
                groups.append(group)
        return Group(gdef["name"], index, tuple(slots), tuple(groups)), address

    def _factor(self, point: dict, prefix: str, own: set[str]) -> str | int | None:
        """A point's scale factor: the point in its own group, else the model's (as
        pysunspec2 looks for it), by its name in the map; or a constant exponent."""
        factor = point.get("sf")
        if factor is None or isinstance(factor, int):
            return factor
        return f"{prefix}.{factor}" if factor in own else f"{self.key}.{factor}"

    def _count(self, sub: dict, prefix: str, address: int) -> int:
        """How many times a group is there: once, a fixed count, the count a point of the
        model holds, or (count 0) as many as the model's registers hold; never more than fit."""
        count = sub.get("count")
        if count is None:
            return 1
        size = self._size(sub)
        room = max(self.end - address, 0)
        where = f"model {self.model_id} ({self.key}) at {self.start - 2}"
        if count == 0:
            if size == 0:
                return 0
            fits, left = divmod(room, size)
            if left:
                self.leftover = True
                self.warnings.append(
                    f"{where}: {counted(left, 'register')} after {counted(fits, sub['name'] + ' group')} "
                    f"({counted(size, 'register')} each) {'does' if left == 1 else 'do'} not make another: shown raw"
                )
            return fits
        if isinstance(count, str):
            held = self._held(count)
            if held is None:
                self.warnings.append(
                    f"{where}: {count}, the count of its {sub['name']} groups, has no value: none shown"
                )
                return 0
            count = held
        fits = room // size if size else count
        if count > fits:
            self.leftover = True
            self.warnings.append(
                f"{where}: {counted(count, sub['name'] + ' group')} of {size} registers (its {sub['count']}) "
                f"{'does' if count == 1 else 'do'} not fit in its length: {fits} shown, the registers left raw"
            )
            return fits
        return count

    def _held(self, name: str) -> int | None:
        """The raw value of a top-level point the model holds (a count), or None."""
        address = self.top.get(name)
        if address is None or not self.start <= address < self.end:
            return None
        value = self.registers[address - self.start]
        return None if value == 0xFFFF else value

    def _size(self, gdef: dict) -> int:
        """Registers one repeat of a group takes, its nested groups counted."""
        size = sum(point_size(point) for point in gdef.get("points", ()))
        for sub in gdef.get("groups", ()):
            count = sub.get("count")
            if count is None:
                times = 1
            elif isinstance(count, str):
                times = self._held(count) or 0
            else:
                times = count
            size += times * self._size(sub)
        return size


# --- the register map of a layout ------------------------------------------------------------


def map_rows(layout: Layout) -> tuple[dict[str, dict], list[str]]:
    """The register map's rows of a model's points, by name, and the names of points no
    map type carries (eui48 and ipv6addr: a MAC address, an IPv6 address; a string too long
    for one read) or whose scale factor the model's length leaves out."""
    rows: dict[str, dict] = {}
    left_out = []
    for slot in layout.root.every_slot() if layout.root is not None else ():
        row = point_row(slot)
        if row is None:
            left_out.append(slot.name)
        else:
            rows[slot.name] = row
    for name, row in list(rows.items()):
        if row.get("scale_ref", name) not in rows:  # its scale factor is past the model's end
            del rows[name]
            left_out.append(name)
    return rows, left_out


def point_row(slot: Slot) -> dict | None:
    """A point's row in a register map (the keys of registermap.load), or None when no map
    type carries it."""
    point = slot.point
    kind = TYPES[point["type"]]
    if kind.map_type is None or slot.size > MAX_READ_REGISTERS:
        return None  # no map type carries it, or no one read can (model 64411's 150-register string)
    row: dict = {"table": "holding", "address": slot.address, "type": kind.map_type}
    if kind.map_type == "string":
        row["count"] = slot.size
    if isinstance(slot.factor, str):
        row["scale_ref"] = slot.factor
    elif slot.factor:
        row["scale"] = 10.0**slot.factor
    if point.get("units"):
        row["unit"] = point["units"].strip()
    label = point.get("label", "")
    if label:
        row["description"] = label
    if point["type"] in ("enum16", "enum32") and point.get("symbols"):
        row["enum"] = {str(symbol["value"]): symbol["name"] for symbol in point["symbols"]}
    if kind.unimplemented:
        row["invalid"] = list(kind.unimplemented)
    if point.get("access") == "RW":
        row["access"] = "rw"
    return row


def bits_set(slot: Slot, value: int) -> list[str]:
    """A bitfield's set bits, by the names its definition gives them (bit N where it gives none)."""
    names = {symbol["value"]: symbol["name"] for symbol in slot.point.get("symbols", ())}
    return [names.get(bit, f"bit {bit}") for bit in range(32) if value >> bit & 1]


def address_text(registers: list[int]) -> str | None:
    """An eui48 or ipv6addr point's registers as pysunspec2 writes them (None: not implemented)."""
    data = b"".join(register.to_bytes(2, "big") for register in registers)
    if len(data) == 8:  # eui48: the MAC address in the last six bytes
        text = ":".join(f"{byte:02X}" for byte in data[2:])
        return None if text == "FF:FF:FF:FF:FF:FF" else text
    if not any(data):
        return None
    return ":".join(data[i : i + 4].hex().upper() for i in range(0, 16, 4))
