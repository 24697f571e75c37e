"""A named point of a register map: where it lives, how its registers read as a value, and back.

Engineering value = raw × scale + offset, computed in decimal so that a
manual's 0.1 m³/h step gives 22.5, not 22.500000000000004, and so that a
written value can be checked to be a whole number of steps before anything is
sent.
"""

from __future__ import annotations

from decimal import Decimal, InvalidOperation

from mbtool.codec.errors import RequestError
from mbtool.codec.record import field, record
from mbtool.codec.tables import Table, reference
from mbtool.codec.values import TYPES, Value, decode_values, encode_values, parse_value

ON_WORDS = {"on": True, "1": True, "true": True, "off": False, "0": False, "false": False}

PointValue = Value | bool | None


@record
class Point:
    name: str
    table: Table
    address: int  # 0-based wire address
    type: str = "uint16"  # a --type name; "bool" for coils, discrete inputs and bits
    order: str = "ABCD"
    count: int = 1  # registers of a string
    scale: Decimal | None = None
    offset: Decimal | None = None
    unit: str = ""
    description: str = ""
    enum: dict = field(default=None, compare=False)  # raw value -> label
    bit: int | None = None  # one bit (0 = least significant) of a register
    writable: bool = False
    warn: str | None = None  # mbtool check's thresholds (Monitoring Plugins range syntax)
    crit: str | None = None

    @property
    def ref(self) -> str:
        return reference(self.table, self.address)

    @property
    def size(self) -> int:
        """Registers (or bits) the point occupies."""
        if self.table.bits or self.bit is not None:
            return 1
        per = TYPES[self.type].registers
        return self.count if per == 0 else per

    @property
    def end(self) -> int:
        return self.address + self.size

    @property
    def is_bit(self) -> bool:
        return self.table.bits or self.bit is not None

    def value_of(self, raw: list[int] | list[bool]) -> PointValue:
        """The engineering value of the point's registers (or bit) as read."""
        if self.table.bits:
            return bool(raw[0])
        if self.bit is not None:
            return bool(raw[0] >> self.bit & 1)
        value = decode_values(raw, self.type, self.order)[0]
        if self.enum is not None and value in self.enum:
            return self.enum[value]
        if self.scale is None and self.offset is None or isinstance(value, str):
            return value
        return _number(Decimal(repr(value)) * (self.scale or 1) + (self.offset or 0))

    @property
    def floating(self) -> bool:
        """Its numbers are floats, whatever one value is: a float type, or a scaled point
        (22.5 one read, 23 the next)."""
        if self.is_bit or self.type not in TYPES:
            return False
        return self.scale is not None or self.offset is not None or TYPES[self.type].fmt in ("f", "d")

    def number_of(self, value: PointValue) -> int | float | None:
        """The number behind a value, for thresholds and monitoring: an enum label's raw
        value, 1 or 0 for a bit, a number as it is; None for text.  Its type is the point's,
        not the value's: a float point's whole value is a float too, as InfluxDB fixes a
        field's type at its first write and refuses any other after (issue 28)."""
        if isinstance(value, bool):
            return int(value)
        if isinstance(value, str):
            labelled = [raw for raw, label in (self.enum or {}).items() if label == value]
            value = labelled[0] if labelled else None
        return float(value) if value is not None and self.floating else value

    def raw_for(self, text: str) -> int | float | str | bool:
        """The raw value that writes ``text`` (engineering units, an enum label, on/off)."""
        if self.is_bit:
            try:
                return ON_WORDS[text.strip().lower()]
            except KeyError:
                raise RequestError(f"{self.name}: {text} is not on or off") from None
        if self.enum is not None:
            for raw, label in self.enum.items():
                if label.lower() == text.strip().lower():
                    return raw
            if not text.strip().lstrip("-").isdigit():
                labels = ", ".join(self.enum.values())
                raise RequestError(f"{self.name}: {text} is none of {labels}")
        if self.type == "string":
            return text
        try:
            wanted = Decimal(text.strip())
        except InvalidOperation:
            raise RequestError(f"{self.name}: {text} is not a number") from None
        if not wanted.is_finite():
            return parse_value(text, self.type)
        scale, offset = self.scale or Decimal(1), self.offset or Decimal(0)
        raw = (wanted - offset) / scale
        if TYPES[self.type].fmt in ("f", "d"):
            return parse_value(str(raw), self.type)
        if raw != raw.to_integral_value():
            low = raw.to_integral_value(rounding="ROUND_FLOOR")
            nearest = " and ".join(_text(r * scale + offset) for r in (low, low + 1))
            raise RequestError(
                f"{self.name}: {text} is not a whole number of steps of {_text(scale)}"
                f"{' from ' + _text(offset) if offset else ''}; the nearest writable values are {nearest}"
            )
        try:
            return parse_value(str(int(raw)), self.type)
        except RequestError as error:
            raise RequestError(
                f"{self.name}: {text} {self.unit}".rstrip() + f" is raw {int(raw)}: {error}"
            ) from None

    def registers_for(self, text: str) -> list[int]:
        """The registers that carry ``text`` (not for bits: see ``raw_for``)."""
        return self.registers_of(self.raw_for(text))

    def registers_of(self, raw: int | float | str) -> list[int]:
        """The registers that carry a raw value (``raw_for``'s), in the point's order."""
        registers = encode_values([raw], self.type, self.order)
        if self.type == "string":
            if len(registers) > self.count:
                raise RequestError(
                    f"{self.name}: {raw} needs {len(registers)} registers, the point has {self.count}"
                )
            registers += [0] * (self.count - len(registers))
        return registers


def _number(value: Decimal) -> int | float:
    return int(value) if value == value.to_integral_value() else float(value)


def _text(value: Decimal) -> str:
    return str(_number(value))
