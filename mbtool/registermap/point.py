"""A named point of a register map: where it lives, how its registers read as a value, and back.

Engineering value = raw × scale + offset, computed in decimal so that a
manual's 0.1 m³/h step gives 22.5, not 22.500000000000004, and so that a
written value can be checked to be a whole number of steps before anything is
sent.  A SunSpec point's scale is read from the device instead: value = raw ×
10^sf, where sf is the value of the point its ``scale_ref`` names (a ``sunssf``
register); a scale factor with no value (SunSpec's 0x8000, "not implemented")
leaves the point with none.

A float register holding NaN or ±Infinity reads as that, scaled or not, as IEEE 754
arithmetic has it: NaN stays NaN, and ±Infinity times the scale keeps its sign (or flips
it, for a negative scale) whatever the offset.  A scaled value beyond a double's range is
±Infinity too, so every value is a number a double holds and every output can carry it.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Callable, Sequence
from decimal import MAX_EMAX, MIN_EMIN, Context, Decimal, InvalidOperation, localcontext

from mbtool.codec.errors import RequestError
from mbtool.codec.record import field, record
from mbtool.codec.tables import Table, reference
from mbtool.codec.values import (
    TYPES,
    Value,
    encode_values,
    float_value,
    integer_value,
    value_decoder,
)
from mbtool.errors import UsageError

ON_WORDS = {"on": True, "1": True, "true": True, "off": False, "0": False, "false": False}

PointValue = Value | bool | None
DOUBLE_MAX = Decimal(sys.float_info.max)  # the largest finite double
UNBOUNDED = Context(Emax=MAX_EMAX, Emin=MIN_EMIN)  # a written value's arithmetic: see raw_for


class NoScaleFactor(RequestError):
    """A scaled point (``scale_ref``) written without the value of its scale factor: not
    read yet, or the device has none (SunSpec's 0x8000)."""


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
    enum: dict | None = field(default=None, compare=False)  # raw value -> label
    bit: int | None = None  # one bit (0 = least significant) of a register
    writable: bool = False
    warn: str | None = None  # mbtool check's thresholds (Monitoring Plugins range syntax)
    crit: str | None = None
    invalid: frozenset = field(default=frozenset(), compare=False)  # raw values meaning no data
    # The point whose value is this one's power-of-ten scale factor (SunSpec's sunssf).
    scale_ref: Point | None = field(default=None, compare=False)
    # What every read of the point asks, worked out once (__post_init__): a map polled reads it
    # again and again.  ``ref``: its Modicon reference; ``_decode``: how its registers read as values.
    ref: str = field(init=False, compare=False)
    _decode: Callable[[Sequence[int]], list[Value]] | None = field(init=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "ref", reference(self.table, self.address))
        registers = not (self.table.bits or self.bit is not None) and self.type in TYPES
        object.__setattr__(self, "_decode", value_decoder(self.type, self.order) if registers else None)

    @property
    def named(self) -> str:
        """The point as a message names it: ``voltage (30001)``, or its reference once when it
        is named by it (``40011``: a plant device's read)."""
        return self.ref if self.name == self.ref else f"{self.name} ({self.ref})"

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

    def value_of(self, raw: Sequence[int], scale_factor: int | None = None) -> PointValue:
        """The engineering value of the point's registers (or bit) as read; ``scale_factor``:
        the value of the ``scale_ref`` point, read with it (None: it has none)."""
        if self.table.bits:
            return bool(raw[0])
        if self.bit is not None:
            return bool(raw[0] >> self.bit & 1)
        assert self._decode is not None  # a register point's decoder, set by __post_init__
        value = self._decode(raw)[0]
        if self.invalid and self.is_invalid(value):
            return None  # the device has no value to give: never a label, never scaled
        if self.enum is not None and value in self.enum:  # a float's whole values too: 2.0 == 2
            return self.enum[value]
        scale = self.scale_for(scale_factor)
        if scale is None and self.scale_ref is not None:
            return None  # a value without its scale factor is no value
        if scale is None and self.offset is None or isinstance(value, str):
            return value
        # Decimal keeps NaN and ±Infinity as IEEE 754 does (repr gives 'nan', 'inf').
        return _number(Decimal(repr(value)) * (scale or 1) + (self.offset or 0))

    def scale_for(self, scale_factor: int | None) -> Decimal | None:
        """The scale that applies: the map's, or 10^sf from the ``scale_ref`` point's value
        (None when that point has no value)."""
        if self.scale_ref is None:
            return self.scale
        return None if scale_factor is None else Decimal(1).scaleb(scale_factor)

    def is_invalid(self, value) -> bool:
        """Whether a raw value is one the map calls no data; NaN is one when the map lists
        it (a NaN equals nothing, itself included, so it is looked for as NaN)."""
        if value in self.invalid:
            return True
        return (
            isinstance(value, float)
            and math.isnan(value)
            and any(isinstance(known, float) and math.isnan(known) for known in self.invalid)
        )

    def no_label(self, value: PointValue) -> bool:
        """Whether a value is one the point's enum gives no label: a number (a raw value
        the map does not name, or a float's fraction, or NaN), shown as such."""
        return self.enum is not None and value is not None and not isinstance(value, str)

    @property
    def floating(self) -> bool:
        """Its numbers are floats, whatever one value is: a float type, or a scaled point
        (22.5 one read, 23 the next)."""
        if self.is_bit or self.type not in TYPES:
            return False
        scaled = self.scale is not None or self.offset is not None or self.scale_ref is not None
        return scaled or TYPES[self.type].fmt in ("f", "d")

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

    def raw_for(
        self, text: str, nonfinite: bool = False, scale_factor: int | None = None
    ) -> int | float | str | bool:
        """The raw value that writes ``text`` (engineering units, an enum label, on/off),
        checked against the point's type after scaling: every error names the point.
        ``nonfinite``: a float point may be written nan or inf.  ``scale_factor``: the value
        the ``scale_ref`` point holds now, which the write undoes."""
        if self.is_bit:
            try:
                return ON_WORDS[text.strip().lower()]
            except KeyError:
                raise UsageError(f"{self.name}: {text} is not on or off") from None
        wanted = _decimal(text)
        if self.enum is not None:
            for raw, label in self.enum.items():
                if label.lower() == text.strip().lower():
                    return raw
            if wanted is None:
                labels = ", ".join(self.enum.values())
                raise UsageError(f"{self.name}: {text} is none of {labels}")
        if self.type == "string":
            return text
        if wanted is None:
            raise UsageError(f"{self.name}: {text} is not a number")
        floating = TYPES[self.type].fmt in ("f", "d")
        if not wanted.is_finite() and not floating:
            raise UsageError(f"{self.name}: {text} is not a number a {self.type} can hold")
        if self.scale_ref is not None and scale_factor is None:
            raise NoScaleFactor(
                f"{self.name}: its scale factor, {self.scale_ref.name}, has no value: {text} cannot be scaled"
            )
        # Decimal's own exponent range (1e999999) is no limit on what a user may type: past
        # it a value is out of the point's range, which the type's check says, not Overflow.
        with localcontext(UNBOUNDED):
            scale, offset = self.scale_for(scale_factor) or Decimal(1), self.offset or Decimal(0)
            raw = (wanted - offset) / scale if wanted.is_finite() else wanted
            # The value named in an error: the user's, and the raw one too when scaling made it.
            shown = text.strip()
            if wanted.is_finite() and raw != wanted:
                shown = f"{shown} {self.unit}".rstrip() + f" (raw {_raw_text(raw)})"
            try:
                if floating:
                    return float_value(raw, self.type, shown, nonfinite)
                if raw != raw.to_integral_value():
                    low = raw.to_integral_value(rounding="ROUND_FLOOR")
                    nearest = " and ".join(_text(r * scale + offset) for r in (low, low + 1))
                    raise UsageError(
                        f"{text} is not a whole number of steps of {_text(scale)}"
                        f"{' from ' + _text(offset) if offset else ''}; the nearest writable values are {nearest}"
                    )
                return integer_value(raw, self.type, shown)
            except (RequestError, UsageError) as error:  # the codec's range of the type, or the steps
                raise UsageError(f"{self.name}: {error}") from None

    def held(self, text: str, raw: int | float | str | bool, scale_factor: int | None = None) -> PointValue:
        """What the point holds once ``raw`` (``raw_for(text)``'s) is written, when that is not
        the decimal ``text`` names: a float32 holds about 7 digits, so 16777217 is written as
        16777216.  None when it is the value given (and for every type but the floats)."""
        if self.is_bit or TYPES[self.type].fmt not in ("f", "d"):
            return None
        wanted = _decimal(text)
        if wanted is None or not wanted.is_finite():
            return None
        value = self.value_of(self.registers_of(raw), scale_factor)
        return None if Decimal(repr(value)) == wanted else value

    def registers_for(self, text: str) -> list[int]:
        """The registers that carry ``text`` (not for bits: see ``raw_for``)."""
        return self.registers_of(self.raw_for(text))

    def registers_of(self, raw: int | float | str) -> list[int]:
        """The registers that carry a raw value (``raw_for``'s), in the point's order."""
        registers = encode_values([raw], self.type, self.order)
        if self.type == "string":
            if len(registers) > self.count:
                raise UsageError(
                    f"{self.name}: {raw} needs {len(registers)} registers, the point has {self.count}"
                )
            registers += [0] * (self.count - len(registers))
        return registers


def _number(value: Decimal) -> int | float:
    """A whole number as an int, else a float; NaN, ±Infinity and anything beyond a
    double's range as the double it is (±Infinity for the last)."""
    if value == value.to_integral_value() and value.copy_abs() <= DOUBLE_MAX:
        return int(value)
    return float(value)


def _raw_text(raw: Decimal) -> str:
    """A raw value in an error: 40000, 0.3333333333333333333333333333, 1E+310."""
    if raw == raw.to_integral_value() and raw.adjusted() < 20:
        return str(int(raw))
    return str(raw.normalize())


def _decimal(text: str) -> Decimal | None:
    """A number as the user types it: a decimal, or 0x hex as every other value takes."""
    text = text.strip()
    try:
        if text.lower().lstrip("+-").startswith("0x"):
            return Decimal(int(text, 16))
        return Decimal(text)
    except (InvalidOperation, ValueError):
        return None


def _text(value: Decimal) -> str:
    return str(_number(value))
