"""Fields of a PDU as decode, --hex, --dry-run and the bus monitor show them.

Each function code's records (``Request`` and ``Response`` subclasses) dissect
their own layout with a classmethod ``dissect(pdu[, request])``, beside the
``decode`` that reads the same bytes, from the pieces here.  A dissection reads
what is there: it is shown for a PDU that does not decode too, so it never
raises on short input (codec.describe cuts it short where the bytes end).
"""

from __future__ import annotations

from mbtool.codec.record import record


@record
class Field:
    name: str  # one token
    raw: bytes  # the bytes on the wire it came from
    value: object
    text: str | None = None  # for people; None: str(value)


def u16(pdu: bytes, at: int, name: str, text: str | None = None) -> Field:
    value = int.from_bytes(pdu[at : at + 2], "big")
    return Field(
        name, bytes(pdu[at : at + 2]), value, text if text is not None else f"{value} (0x{value:04X})"
    )


def count16(pdu: bytes, at: int, name: str) -> Field:
    """A quantity or a count: shown as a plain number."""
    return u16(pdu, at, name, str(int.from_bytes(pdu[at : at + 2], "big")))


def u8(pdu: bytes, at: int, name: str, text: str | None = None) -> Field:
    return Field(name, bytes(pdu[at : at + 1]), pdu[at], text if text is not None else str(pdu[at]))


def register_fields(
    pdu: bytes, start: int, end: int, first: int | None, name: str = "register"
) -> list[Field]:
    """Registers from ``start`` to ``end``, labelled by address (``first``) or by index."""
    return [
        u16(pdu, at, f"{name}[{first + i if first is not None else i}]")
        for i, at in enumerate(range(start, end - 1, 2))
    ]


def bit_fields(
    pdu: bytes, start: int, end: int, first: int | None, count: int | None, what: str
) -> list[Field]:
    """Packed bits (spec §1: LSB first), a field a byte, each bit named ON or OFF."""
    out = []
    for i, at in enumerate(range(start, end)):
        byte = pdu[at]
        low = 8 * i
        n = 8 if count is None else max(0, min(8, count - low))
        states = " ".join("ON" if byte >> b & 1 else "OFF" for b in range(n or 8))
        where = (
            f"{what} {first + low}-{first + low + max(n, 1) - 1}"
            if first is not None
            else f"bits {low}-{low + 7}"
        )
        out.append(Field(f"data[{i}]", bytes([byte]), byte, f"0x{byte:02X} {where}: {states}"))
    return out


def busy_status(pdu: bytes, at: int) -> Field:
    """FC 0B / 0C's status word: FFFF busy, 0000 idle (spec §4)."""
    value = int.from_bytes(pdu[at : at + 2], "big")
    meaning = {0xFFFF: "busy", 0x0000: "idle"}.get(value, "neither busy (FFFF) nor idle (0000)")
    return Field("status", bytes(pdu[at : at + 2]), value, f"0x{value:04X} {meaning}")


def printable(data: bytes) -> str:
    return "".join(chr(b) if 0x20 <= b < 0x7F else "." for b in data)


def text_of(value: bytes) -> str:
    """An identification object as text; bytes that are not printable text as hex."""
    try:
        text = value.decode("utf-8")
    except UnicodeDecodeError:
        return value.hex(" ").upper()
    return text if text.isprintable() else value.hex(" ").upper()
