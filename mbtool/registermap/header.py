"""What a map says of its device, beside the points: the ``[device]`` header of the maps
mbtool ships (``mbtool maps``), which a user's own map may carry too.

::

    [device]
    manufacturer = "Eastron"
    model = "SDM630"
    kind = "meter"               # meter, inverter, battery, charger or io
    transport = "rtu"            # rtu, tcp or both
    firmware = "v2 and later"    # free text: the range the map was written for
    default_unit = 1             # the unit id the device leaves the factory with
    baud = 9600                  # serial defaults, as a profile names them
    parity = "N"
    stopbits = 1
    source = "Eastron SDM630 Modbus Protocol, V1.5, pp. 3-9"

    [[device.signature]]         # how `mbtool identify` recognises the device: reads only
    ref = 30001
    type = "float32"
    within = [100, 300]          # a line voltage

    [[device.signature]]
    ref = 464513
    equals = 0x0070              # the model code register

A probe is a location (``ref``, or ``table`` and ``address``), a ``type`` and ``order``
(the map's defaults apply) and one expectation: ``equals`` (a value, or a list of the values
it may hold), ``within = [LOW, HIGH]``, ``matches`` (a regular expression a string's text
matches whole), ``answers = true`` (any value) or ``refuses = true`` (an exception reply, as
a device gives for a register it does not have).  Every probe is read as it is, unscaled.
Everything is checked when the map is loaded: one line naming the file and the key.
"""

from __future__ import annotations

import math
import re
from typing import Any

from mbtool.codec.record import record
from mbtool.registermap.point import Point

HEADER_KEYS = {
    "manufacturer": "the maker's name, such as Eastron",
    "model": "the model, such as SDM630",
    "kind": "meter, inverter, battery, charger or io",
    "transport": "rtu, tcp or both",
    "firmware": "the firmware versions the map is for (text)",
    "default_unit": "the unit id the device leaves the factory with (a TCP device may answer at 255)",
    "baud": "the serial default, such as 9600",
    "parity": 'the serial default: "N", "E" or "O"',
    "stopbits": "the serial default: 1 or 2",
    "source": "the manual the map comes from: title, version, page",
    "signature": "the probes mbtool identify reads: [[device.signature]]",
}
KINDS = ("meter", "inverter", "battery", "charger", "io")
TRANSPORTS = ("rtu", "tcp", "both")
BAUDS = (1200, 2400, 4800, 9600, 19200, 38400, 57600, 115200)
PARITIES = ("N", "E", "O")
EXPECTATIONS = ("equals", "within", "matches", "answers", "refuses")
PROBE_KEYS = ("ref", "table", "address", "type", "order", "count", *EXPECTATIONS)


@record
class Probe:
    """One read of a signature and what it must give."""

    point: Point  # where, and how its registers read (never scaled)
    expect: str  # one of EXPECTATIONS
    wanted: Any  # equals: a tuple of values; within: (low, high); matches: a pattern

    def judge(self, value, refused: bool) -> bool:
        """Whether the reply fits: ``value`` as the point's registers read (None when the
        device refused the read, ``refused`` True)."""
        if self.expect == "refuses":
            return refused
        if refused:
            return False
        if self.expect == "answers":
            return True
        if self.expect == "equals":
            return value in self.wanted
        if self.expect == "within":
            return isinstance(value, int | float) and self.wanted[0] <= value <= self.wanted[1]
        return isinstance(value, str) and self.wanted.fullmatch(value) is not None

    def describe(self) -> str:
        """The probe in words: ``30001 float32 in 100..300``."""
        where = f"{self.point.ref} {self.point.type}"
        if self.expect == "refuses":
            return f"{self.point.ref} refuses"
        if self.expect == "answers":
            return f"{self.point.ref} answers"
        if self.expect == "within":
            return f"{where} in {_number(self.wanted[0])}..{_number(self.wanted[1])}"
        if self.expect == "matches":
            return f"{where} matches {self.wanted.pattern}"
        shown = [_shown(value, self.point.type) for value in self.wanted]
        return f"{where} = {' or '.join(shown)}"

    @property
    def weight(self) -> int:
        """How much a match says: a model code says more than a value in a range, which
        says more than a register that merely answers."""
        return {"equals": 4, "matches": 3, "within": 2, "refuses": 1, "answers": 1}[self.expect]


@record
class DeviceHeader:
    manufacturer: str = ""
    model: str = ""
    kind: str = ""
    transport: str = ""
    firmware: str = ""
    default_unit: int | None = None
    baud: int | None = None
    parity: str = ""
    stopbits: int | None = None
    source: str = ""
    signature: tuple = ()  # Probe, in the order they are read

    def serial(self) -> dict:
        """The serial defaults the map gives, by their profile keys."""
        given = {"baud": self.baud, "parity": self.parity, "stopbits": self.stopbits}
        return {key: value for key, value in given.items() if value not in (None, "")}


def _number(value) -> str:
    return str(int(value)) if float(value).is_integer() else str(value)


def _shown(value, kind: str) -> str:
    if isinstance(value, str):
        return repr(value)
    if kind in ("uint16", "uint32", "uint64", "hex") and isinstance(value, int):
        return f"0x{value:04X}"
    return _number(value)


def device_header(header: dict, make_point, fail) -> DeviceHeader | None:
    """The header keys of a ``[device]`` table, checked (None when it has none).

    ``make_point(name, row)`` checks a probe's location and type as a point's;
    ``fail(key, why)`` is the loader's error for a key of [device]."""
    if not header:
        return None
    fields: dict = {}
    for key in ("manufacturer", "model", "firmware", "source"):
        if key in header:
            fields[key] = _text(header[key], key, fail)
    for key, choices in (("kind", KINDS), ("transport", TRANSPORTS)):
        if key in header:
            value = _text(header[key], key, fail).lower()
            if value not in choices:
                raise fail(key, f"{header[key]} is none of {', '.join(choices)}")
            fields[key] = value
    if "default_unit" in header:
        fields["default_unit"] = _whole(header["default_unit"], "default_unit", 0, 255, fail)
    if "baud" in header:
        fields["baud"] = _whole(header["baud"], "baud", 1, 10_000_000, fail)
        if fields["baud"] not in BAUDS:
            raise fail("baud", f"{fields['baud']} is not a rate devices use ({', '.join(map(str, BAUDS))})")
    if "parity" in header:
        parity = _text(header["parity"], "parity", fail).upper()
        parity = {"NONE": "N", "EVEN": "E", "ODD": "O"}.get(parity, parity)
        if parity not in PARITIES:
            raise fail("parity", f'{header["parity"]} is none of "N", "E", "O"')
        fields["parity"] = parity
    if "stopbits" in header:
        fields["stopbits"] = _whole(header["stopbits"], "stopbits", 1, 2, fail)
    if "signature" in header:
        fields["signature"] = _signature(header["signature"], make_point, fail)
    return DeviceHeader(**fields)


def _text(value, key: str, fail) -> str:
    if not isinstance(value, str) or not value.strip():
        raise fail(key, f"{value!r} is not text")
    if not value.isprintable():
        raise fail(key, f"{value!r} is written on one line: no control characters")
    return value.strip()


def _whole(value, key: str, low: int, high: int, fail) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
        raise fail(key, f"{value!r} is not a whole number in {low}..{high}")
    return value


def _signature(probes, make_point, fail) -> tuple[Probe, ...]:
    if not isinstance(probes, list) or not probes or not all(isinstance(p, dict) for p in probes):
        raise fail(
            "signature",
            "a list of probes: [[device.signature]] with ref and one of " + ", ".join(EXPECTATIONS),
        )
    out = []
    for number, row in enumerate(probes, 1):
        key = f"signature {number}"
        unknown = [name for name in row if name not in PROBE_KEYS]
        if unknown:
            raise fail(key, f"unknown key {unknown[0]} (known: {', '.join(PROBE_KEYS)})")
        given = [name for name in EXPECTATIONS if name in row]
        if len(given) != 1:
            raise fail(key, f"give one expectation of {', '.join(EXPECTATIONS)}, not {len(given)}")
        expect = given[0]
        location = {name: row[name] for name in row if name not in EXPECTATIONS}
        point = make_point(key, location)  # as the map's points read: [device] type and order apply
        out.append(Probe(point, expect, _wanted(expect, row[expect], point, key, fail)))
    return tuple(out)


def _wanted(expect: str, wanted, point: Point, key: str, fail):
    kind = point.type
    if expect in ("answers", "refuses"):
        if wanted is not True:
            raise fail(key, f"{expect} = true, or leave it out")
        return None
    if expect == "matches":
        if kind != "string" or not isinstance(wanted, str):
            raise fail(key, 'matches is a regular expression for a string\'s text (type = "string")')
        try:
            return re.compile(wanted)
        except re.error as error:
            raise fail(key, f"matches: {error}") from None
    if expect == "within":
        if kind in ("string", "bool"):
            raise fail(key, f"within is a range of numbers, and a {kind} holds none")
        if (
            not isinstance(wanted, list)
            or len(wanted) != 2
            or not all(isinstance(x, int | float) and not isinstance(x, bool) for x in wanted)
            or not all(math.isfinite(x) for x in wanted)
            or wanted[0] > wanted[1]
        ):
            raise fail(key, "within = [LOW, HIGH], two numbers, LOW first")
        return (wanted[0], wanted[1])
    values = wanted if isinstance(wanted, list) else [wanted]
    if not values:
        raise fail(key, "equals: a value, or a list of the values it may hold")
    for value in values:
        fits = (
            isinstance(value, bool)
            if kind == "bool"
            else isinstance(value, str)
            if kind == "string"
            else isinstance(value, int | float) and not isinstance(value, bool)
        )
        if not fits:
            raise fail(key, f"equals: {value!r} is not a value a {kind} reads as")
    return tuple(values)
