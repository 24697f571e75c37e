"""Typed values carried in 16-bit registers, in any of the four byte orders (spec §1).

Registers are big-endian on the wire, but devices disagree on how a 32- or
64-bit value spreads over several registers.  The order names the bytes of a
32-bit value ABCD as they sit in the registers:

* ABCD: big-endian words, big-endian bytes (the Modbus default)
* CDAB: words swapped (the low word first), bytes big-endian
* BADC: bytes swapped inside each word, words big-endian
* DCBA: everything little-endian

For 64-bit types the same two swaps apply (word order reversed, bytes swapped).
For 16-bit types only the byte swap means anything.
"""

from __future__ import annotations

import math
import struct
import sys
from collections.abc import Callable, Sequence

from mbtool.codec.errors import RequestError
from mbtool.codec.record import record

ORDERS = ("ABCD", "CDAB", "BADC", "DCBA")


@record
class ValueType:
    name: str
    registers: int  # registers per value; 0 for string (as many as asked)
    fmt: str  # struct format of the big-endian value ("" for hex/string)

    @property
    def integer(self) -> bool:
        """Its values are whole numbers (Python ints)."""
        return self.fmt in ("H", "h", "I", "i", "Q", "q")


TYPES = {
    t.name: t
    for t in (
        ValueType("uint16", 1, "H"),
        ValueType("int16", 1, "h"),
        ValueType("uint32", 2, "I"),
        ValueType("int32", 2, "i"),
        ValueType("float32", 2, "f"),
        ValueType("uint64", 4, "Q"),
        ValueType("int64", 4, "q"),
        ValueType("float64", 4, "d"),
        ValueType("hex", 1, ""),
        ValueType("string", 0, ""),
    )
}

Value = int | float | str


def _swap_words(words: list[int], order: str) -> list[int]:
    if order in ("CDAB", "DCBA"):
        words = words[::-1]
    if order in ("BADC", "DCBA"):
        words = [((w & 0xFF) << 8) | (w >> 8) for w in words]
    return words


def _bytes_only(order: str) -> str:
    """Types of one register at a time (hex, string): only the byte swap applies."""
    return "BADC" if order in ("BADC", "DCBA") else "ABCD"


def _registers_of(data: bytes, order: str) -> list[int]:
    words = list(struct.unpack(f">{len(data) // 2}H", data))
    return _swap_words(words, order)


def _bytes_of(registers: Sequence[int], order: str) -> bytes:
    # The swaps are their own inverse, so the same function undoes them.
    return struct.pack(f">{len(registers)}H", *_swap_words(list(registers), order))


def _printable(data: bytes) -> str:
    """Text as latin-1, with control bytes shown as \\xNN so a terminal is never garbled."""
    return "".join(chr(b) if 32 <= b < 127 or b >= 160 else f"\\x{b:02x}" for b in data)


_FLOAT32 = struct.Struct(">f")
FLOAT32_MIN_NORMAL = 1.1754943508222875e-38


def shortest_float32(value: float) -> float:
    """The float32 as the shortest decimal that reads back as it (123.456, not
    123.45600128173828): what the device's manual and its display show.  A double whose
    repr is that decimal, so every output format prints it alike."""
    if not math.isfinite(value):
        return value
    # For a normal float32 the 6-digit rounding is the shortest form whenever 6 digits or
    # fewer suffice (%g drops trailing zeros); a subnormal's coarse spacing may admit a
    # shorter one, so there every length is tried.
    for digits in (6, 7, 8) if abs(value) >= FLOAT32_MIN_NORMAL else range(1, 9):
        short = float(f"{value:.{digits}g}")
        if _FLOAT32.unpack(_FLOAT32.pack(short))[0] == value:
            return short
    return float(f"{value:.9g}")  # nine significant digits always suffice for a float32


def registers_needed(type_name: str, count: int) -> int:
    """Registers to read for ``count`` values; a string counts registers (2 characters each)."""
    per = TYPES[type_name].registers
    return count if per == 0 else count * per


def value_decoder(type_name: str, order: str = "ABCD") -> Callable[[Sequence[int]], list[Value]]:
    """How a block of registers reads as values of the type in the order: chosen once, so a
    polling loop decodes each reply in one call, without asking again what the type is."""
    kind = TYPES[type_name]
    byte_order = _bytes_only(order)  # what a type of one register at a time heeds
    if kind.name == "string":
        return lambda registers: [_printable(_bytes_of(registers, byte_order).rstrip(b"\x00"))]
    if kind.name == "hex":
        return lambda registers: [f"0x{w:04X}" for w in _swap_words(list(registers), byte_order)]
    size = kind.registers
    if kind.fmt == "H" and byte_order == "ABCD":
        return list  # uint16 as on the wire: the registers themselves
    float32 = kind.fmt == "f"
    if (byte_order if size == 1 else order) != "ABCD":

        def swapped(registers: Sequence[int]) -> list[Value]:
            values = [
                struct.unpack(">" + kind.fmt, _bytes_of(registers[i : i + size], order))[0]
                for i in range(0, len(registers) - size + 1, size)
            ]
            return list(map(shortest_float32, values)) if float32 else values

        return swapped

    def big_endian(registers: Sequence[int]) -> list[Value]:
        # As on the wire: the whole block in one unpack.
        count = len(registers) // size
        values = struct.unpack(
            f">{count}{kind.fmt}", struct.pack(f">{count * size}H", *registers[: count * size])
        )
        return list(map(shortest_float32, values)) if float32 else list(values)

    return big_endian


def decode_values(registers: Sequence[int], type_name: str, order: str = "ABCD") -> list[Value]:
    """The values in the registers: one a value's worth of registers (a string: one in all)."""
    return value_decoder(type_name, order)(registers)


def value_addresses(type_name: str, first: int, registers: int) -> list[int]:
    """Where each value of a block of ``registers`` registers from ``first`` starts."""
    size = TYPES[type_name].registers
    if size == 0:  # a string: one value, the whole block
        return [first]
    return list(range(first, first + registers - registers % size, size))


FLOAT_MAX = {"f": 3.4028234663852886e38, "d": sys.float_info.max}  # the largest finite of each


def parse_value(text: str, type_name: str, nonfinite: bool = False) -> Value:
    """A value typed by the user, checked against the type's range; RequestError if not.
    ``nonfinite``: nan and inf are written as such (a float type only)."""
    kind = TYPES[type_name]
    if kind.name == "string":
        return text
    if kind.fmt in ("f", "d"):
        return float_value(text, type_name, text, nonfinite)
    try:
        value = int(text, 0)
    except ValueError:
        raise RequestError(f"{text} is not a valid {type_name} value") from None
    return integer_value(value, type_name, text)


def float_value(number, type_name: str, shown: str, nonfinite: bool = False) -> float:
    """``number`` (text or a Decimal) as the float type holds it.  A decimal beyond the
    type's range is refused: float() would make it an infinity, and struct would send
    7F 80 00 00 for a value the user never typed.  nan and inf only with ``nonfinite``."""
    from decimal import Decimal, InvalidOperation  # noqa: PLC0415 - decimal, 1 ms: a float written only

    kind = TYPES[type_name]
    try:
        exact = number if isinstance(number, Decimal) else Decimal(str(number).strip())
    except InvalidOperation:
        exact = None
    if exact is None or exact.is_snan():
        raise RequestError(f"{shown} is not a valid {type_name} value")
    if not exact.is_finite():
        if not nonfinite:
            raise RequestError(f"{shown} is not a finite number (--allow-nonfinite writes it)")
        return float(exact)
    value = float(exact)  # correctly rounded, as float(text) is
    if not abs(value) <= FLOAT_MAX[kind.fmt]:
        raise RequestError(f"{shown} is out of {type_name}'s range")
    return value


def integer_value(value, type_name: str, shown: str) -> int:
    """``value`` (an int, or a whole Decimal) as an int when the integer type holds it;
    RequestError naming ``shown`` if not (checked first: 1e999999 is never made an int)."""
    kind = TYPES[type_name]
    bits = 16 * kind.registers
    low, high = (-(1 << (bits - 1)), (1 << (bits - 1)) - 1) if kind.fmt.islower() else (0, (1 << bits) - 1)
    if kind.name == "hex":
        low = 0
    if not low <= value <= high:
        raise RequestError(f"{shown} is out of range {low}..{high} for {type_name}")
    return int(value)


def encode_values(values: list[Value], type_name: str, order: str = "ABCD") -> list[int]:
    """Registers that carry the values, in the given order."""
    kind = TYPES[type_name]
    if kind.name == "string":
        data = "".join(str(v) for v in values).encode("latin-1", errors="replace")
        if len(data) % 2:
            data += b"\x00"
        return _registers_of(data, _bytes_only(order))
    if kind.name == "hex":
        return _swap_words([int(v) for v in values], _bytes_only(order))
    registers: list[int] = []
    for value in values:
        registers += _registers_of(struct.pack(">" + kind.fmt, value), order)
    return registers


def parse_register(text: str) -> int:
    """A plain register value: -32768..65535, negatives stored as two's complement."""
    try:
        value = int(text, 0)
    except ValueError:
        hint = ""
        try:
            float(text)
            hint = " (a register holds a whole number: for a fraction use --type float32)"
        except ValueError:
            pass
        raise RequestError(f"{text} is not a valid register value{hint}") from None
    if not -0x8000 <= value <= 0xFFFF:
        raise RequestError(f"register value {text} is out of range -32768..65535")
    return value & 0xFFFF


def parse_registers(texts, type_name: str, order: str = "ABCD", nonfinite: bool = False) -> list[int]:
    """The registers for values as a user types them, each checked against its type
    (``nonfinite``: a float may be nan or inf)."""
    if type_name == "uint16":
        return [parse_register(text) for text in texts]  # -32768..65535, as the contract says
    return encode_values([parse_value(text, type_name, nonfinite) for text in texts], type_name, order)
