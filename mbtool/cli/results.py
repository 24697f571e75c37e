"""What a command learned, as records: values at addresses (``Result``), a register map's
points (``Points``), named rows (``Report``); and each as the plain data JSON carries.

The sinks (``cli/sinks/``, a module a format) turn these into text in the run's format;
a record knows no format.  What every format says alike of a record (what labels a value,
each value's text, a change of one) is here.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

from mbtool.codec.record import field, fields_setter, record


@record
class Result:
    """What a command learned (or wrote): values at addresses, and their context."""

    unit: int
    function: int
    name: str
    address: int
    values: list  # bits, or values of ``type``; {order: value} each with --order all
    type: str | None = None  # None for bits; a register type from codec.values otherwise
    registers: Sequence[int] | None = None  # the raw registers behind typed values, as read
    note: str = ""  # one line for the human, e.g. "broadcast: no device confirms"
    extra: dict | None = None  # more keys for JSON
    refs: list[str] | None = None  # Modicon references of the values (read REF): shown for addresses
    # Where each value starts; the constructor's None: one a value from address (so never None).
    addresses: list[int] = field(default=None)
    texts: list[str] | None = None  # each value as plain, table and CSV say it; None: value_text's

    def __init__(
        self,
        unit: int,
        function: int,
        name: str,
        address: int,
        values: list,
        type: str | None = None,
        registers: Sequence[int] | None = None,
        note: str = "",
        extra: dict | None = None,
        refs: list[str] | None = None,
        addresses: list[int] | None = None,
        texts: list[str] | None = None,
    ) -> None:
        # By hand, its fields one table (codec/record.py): a poll's result copies it.
        _set_fields(
            self,
            {
                "unit": unit,
                "function": function,
                "name": name,
                "address": address,
                "values": values,
                "type": type,
                "registers": registers,
                "note": note,
                "extra": extra,
                "refs": refs,
                # One value a register or a bit, from ``address`` on, unless the command says otherwise.
                "addresses": list(range(address, address + len(values))) if addresses is None else addresses,
                "texts": texts,
            },
        )

    def polled(self, values: list, registers: Sequence[int] | None) -> Result:
        """This read's result with a poll's values and registers: the polls of one read share
        everything else, the very same objects (copied, not worked out again)."""
        fields = self.__dict__.copy()  # the table copied whole: a third of a dict filled anew
        fields["values"] = values
        fields["registers"] = registers
        result = _new(Result)
        _set_fields(result, fields)
        return result

    @property
    def table(self) -> str:
        """The table a read of FC 01-04 read (coils, discrete, input, holding); else the
        function's name."""
        from mbtool.codec.tables import TABLE_OF_READ  # noqa: PLC0415 - -o influx and prom only

        return TABLE_OF_READ.get(self.function, self.name)


_new = object.__new__  # a record made without its __init__: a poll's result's fields are copied
_set_fields = fields_setter(Result)  # a result's fields, set whole (codec/record.py)


def value_text(value: object) -> str:
    if isinstance(value, bool):
        return "1" if value else "0"
    if isinstance(value, float):
        return repr(value)
    if isinstance(value, dict):  # --order all: the value in each word order
        return " ".join(f"{order}={value_text(each)}" for order, each in value.items())
    return str(value)


def labels(result: Result) -> list:
    """What names each item: its reference when the user gave one (read 40108), else its address."""
    return result.refs if result.refs is not None else result.addresses


def value_texts(result: Result) -> list[str]:
    """Each value as plain, table and CSV say it: the command's own words where it gave them
    (write-bit's ``bit 2 on``), else the value's text."""
    return result.texts if result.texts is not None else [value_text(value) for value in result.values]


def by_order(result: Result) -> tuple[str, ...]:
    """The word orders of a --order all result (its values are {order: value}); () otherwise."""
    first = result.values[0] if result.values else None
    return tuple(first) if isinstance(first, dict) else ()


def as_dict(result: Result) -> dict:
    data: dict = {
        "unit": result.unit,
        "function": result.function,
        "name": result.name,
        "address": result.address,
    }
    if result.type:
        data["type"] = result.type
    data["values"] = result.values
    data["addresses"] = result.addresses
    if result.refs is not None:
        data["refs"] = result.refs
    # The registers behind typed values, or behind plain ones echoed as typed (-5: 65531).
    if result.registers is not None and (
        result.type not in (None, "uint16") or list(result.registers) != result.values
    ):
        data["registers"] = result.registers
    data.update(result.extra or {})
    return data


@record
class PollsOfRead:
    """How the replies of one read (of one request, polled or once) become what it shows:
    ``read``, the result its polls share (all but their values and registers), ``data_of(reply)``,
    what a reply carries, ``decode(data)``, its values, and ``raw``: that data shown as the
    registers.  Polled, a reply is shown as ``read`` and its values, no Result made
    (cli.poll_output's DeferredRead); called, the reply's whole result."""

    read: Result
    data_of: Callable[[Any], Sequence]
    decode: Callable[[Sequence], list]
    raw: bool

    def __call__(self, reply) -> Result:
        data = self.data_of(reply)
        return self.read.polled(self.decode(data), data if self.raw else None)


# --- a register map's points: name, value, unit ------------------------------------------


@record
class PointRow:
    """One point of a register map as read: ``value`` in engineering units (or its enum
    label, or on/off), ``raw`` the registers (or bits) it came from."""

    name: str
    value: object
    unit: str
    ref: str
    raw: tuple
    bits: bool  # a coil or discrete input: raw holds bits, not registers
    description: str = ""
    number: int | float | None = None  # the number behind the value (Point.number_of)
    no_label: bool = False  # a value the point's enum does not label (Point.no_label)

    def __init__(
        self,
        name: str,
        value: object,
        unit: str,
        ref: str,
        raw: tuple,
        bits: bool,
        description: str = "",
        number: int | float | None = None,
        no_label: bool = False,
    ) -> None:
        # By hand: one a point a poll (codec/record.py).
        fields = self.__dict__
        fields["name"] = name
        fields["value"] = value
        fields["unit"] = unit
        fields["ref"] = ref
        fields["raw"] = raw
        fields["bits"] = bits
        fields["description"] = description
        fields["number"] = number
        fields["no_label"] = no_label

    @property
    def shown(self) -> str:
        return point_text(self.value) + (" (no label)" if self.no_label else "")


INVALID = "invalid"  # a raw value the map's invalid key names: the device has no value to give


def point_text(value: object) -> str:
    """A map's point's value as text: a bit is on or off; no value (the map's invalid key)
    is invalid."""
    if value is None:
        return INVALID
    if isinstance(value, bool):
        return "on" if value else "off"
    return value_text(value)


def reading_text(reading) -> str:
    """A plant's reading (plant.schedule) as read -m shows its point: on/off, invalid, a
    label, or a number (no label)."""
    return point_text(reading.value) + (" (no label)" if reading.point.no_label(reading.value) else "")


@record
class PointFailure:
    """A point of a map the device refused: its name, ref and the device's answer."""

    name: str
    ref: str
    error: str


@record
class Points:
    """What ``read -m MAP`` learned.  Plain: ``NAME VALUE UNIT`` lines; JSON: the unit id,
    the map, and each point's name, value, unit, ref and raw registers; CSV: a row a point.
    The points the device refused (a partial read) are in ``failed``: in JSON and the table,
    and on stderr; plain and CSV lines are values only."""

    unit: int
    source: str  # the map file
    rows: list[PointRow]
    note: str = ""  # one line for the human, e.g. "broadcast: no device confirms"
    failed: Sequence[PointFailure] = ()


def points_heading(points: Points) -> str:
    return f"{points.source} · unit {points.unit}"


def change_parts(what: dict, old, new, unit: str = "") -> tuple[str, str, str]:
    """A value that differs (diff) or changed (--changes): what it is and both values as text.

    ``what`` names a map's point (name, ref) or an address (table, address); a value of
    None is an address a side does not have: "missing".  A point's bit is on or off, as
    read -m shows it."""
    point = "name" in what
    where = f"{what['name']} ({what['ref']})" if point else f"{what['table']} {what['address']}"

    def shown(value) -> str:
        if value is None:
            return "missing"
        return (point_text(value) if point else value_text(value)) + (f" {unit}" if unit else "")

    return where, shown(old), shown(new)


def engineering_unit(unit: str) -> dict:
    """A point's engineering unit as its JSON key, none when it has none: in a record whose
    own "unit" is the unit id, a point's ``"unit": ""`` reads as that id gone missing."""
    return {"unit": unit} if unit else {}


def points_dict(points: Points) -> dict:
    return {
        "unit": points.unit,
        "map": points.source,
        "points": [
            {
                "name": row.name,
                "value": row.value,
                **engineering_unit(row.unit),
                "ref": row.ref,
                "bits" if row.bits else "registers": list(row.raw),
                **({"invalid": True} if row.value is None else {}),
            }
            for row in points.rows
        ],
        **(
            {"failed": [{"name": f.name, "ref": f.ref, "error": f.error} for f in points.failed]}
            if points.failed
            else {}
        ),
    }


# --- structured results: fields, counters, event lists, decoded frames -----------------


@record
class Row:
    """One named item of a Report.

    ``name`` is one token (a script splits the plain line at the first space);
    ``value`` is plain data for JSON; ``text`` is how a person reads it (default:
    the value); ``raw`` the bytes on the wire it came from (offline decoding).
    """

    name: str
    value: object
    text: str | None = None
    raw: bytes | None = None

    @property
    def shown(self) -> str:
        return value_text(self.value) if self.text is None else self.text


@record
class Report:
    """What a command learned that is not a run of addressed values: named rows.

    Plain: one ``NAME VALUE`` line per row.  JSON: ``unit``, ``function``, ``name``,
    then ``data`` (default: each row's name and value).  CSV: ``name,value`` rows
    (plus ``bytes`` when rows carry them).  Table: one rich table.
    """

    unit: int | None
    function: int | None
    name: str
    rows: list[Row]
    data: dict | None = None
    note: str = ""
    title: str = ""  # the table's heading; default name, function code and unit
    header: bool = True  # CSV header (off for the second and later of several reports)


def report_dict(report: Report) -> dict:
    head: dict = {"unit": report.unit, "function": report.function, "name": report.name}
    body = report.data if report.data is not None else {row.name: row.value for row in report.rows}
    return {**head, **body}


@record
class Listing:
    """What a command lists in a shape of its own (a write's items, diff's differences,
    sunspec's models): each format's view of it, worked out when that format is chosen."""

    data: Callable[[], object]  # -o json: the object
    table: (
        Callable[[], tuple[list[str] | None, list[list]]] | None
    )  # -o csv: header (None: none), rows; None: its lines
    lines: Callable[[], list[str]]  # -o plain, and -o table where ``draw`` is None
    draw: Callable[[], None] | None = None  # -o table: draws it (a function of cli/sinks/table.py)
