"""The SunSpec model definitions and the point types they use.

The definitions are the SunSpec Alliance's JSON files, as pysunspec2 ships them
(``models/``, unmodified; ``models/README.md`` says which release).  Each is a group of
points and groups; a point has a name, a type, a size in registers, and may have units,
a scale factor (``sf``: the name of a ``sunssf`` point, or a constant exponent), symbols
(an enum's values, a bitfield's bits) and access RW.
"""

from __future__ import annotations

import json
from functools import cache
from pathlib import Path

from mbtool.codec.record import record

MODELS = Path(__file__).parent / "models"
MARKER = (0x5375, 0x6E53)  # "SunS"
END_MODEL = 0xFFFF
BASES = (40000, 0, 50000)  # where a device may start its chain, in the order looked at


@record
class PointType:
    """A SunSpec point type: its registers, the register-map type that reads it (None: no
    map type carries it), and the raw values that mean "not implemented"."""

    name: str
    registers: int  # 0: a string's, from its definition's size
    map_type: str | None
    unimplemented: tuple = ()


_TYPES = [
    PointType("int16", 1, "int16", (-0x8000,)),
    PointType("uint16", 1, "uint16", (0xFFFF,)),
    PointType("count", 1, "uint16", (0xFFFF,)),
    PointType("acc16", 1, "uint16", (0,)),  # an accumulator that never counted is none
    PointType("enum16", 1, "uint16", (0xFFFF,)),
    PointType("bitfield16", 1, "uint16", (0xFFFF,)),
    PointType("pad", 1, "uint16"),
    PointType("int32", 2, "int32", (-0x80000000,)),
    PointType("uint32", 2, "uint32", (0xFFFFFFFF,)),
    PointType("acc32", 2, "uint32", (0,)),
    PointType("enum32", 2, "uint32", (0xFFFFFFFF,)),
    PointType("bitfield32", 2, "uint32", (0xFFFFFFFF,)),
    PointType("ipaddr", 2, "uint32", (0,)),
    PointType("int64", 4, "int64", (-0x8000000000000000,)),
    PointType("uint64", 4, "uint64", (0xFFFFFFFFFFFFFFFF,)),
    PointType("acc64", 4, "uint64", (0,)),
    PointType("float32", 2, "float32", (float("nan"),)),
    PointType("float64", 4, "float64", (float("nan"),)),
    PointType("string", 0, "string", ("",)),  # NUL bytes only
    PointType("sunssf", 1, "int16", (-0x8000,)),
    PointType("eui48", 4, None),  # a MAC address in the last 6 of 8 bytes
    PointType("ipv6addr", 8, None),
]
TYPES = {kind.name: kind for kind in _TYPES}


class DefinitionError(ValueError):
    """A definition file that cannot be used (never one of those shipped: a test reads them all)."""


@cache
def definition(model_id: int) -> dict | None:
    """The model's definition (its top-level group), or None for an id SunSpec does not define."""
    path = MODELS / f"model_{model_id}.json"
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        return None
    document = json.loads(text)
    if document.get("id") != model_id or not isinstance(document.get("group"), dict):
        raise DefinitionError(f"{path.name}: not the definition of model {model_id}")
    return document["group"]


def known_models() -> list[int]:
    """Every model id a definition is shipped for, in order."""
    return sorted(int(path.stem.removeprefix("model_")) for path in MODELS.glob("model_*.json"))


def point_size(point: dict) -> int:
    """Registers a point of a definition takes: its type's, or a string's size."""
    kind = TYPES.get(point["type"])
    if kind is None:
        raise DefinitionError(f"point {point['name']}: unknown type {point['type']}")
    return kind.registers or int(point["size"])
