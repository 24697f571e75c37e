"""Output that monitoring systems read as it is: InfluxDB line protocol (``-o influx``)
and the Prometheus text exposition format (``-o prom``, ``--textfile``).

Both follow their system's reference to the letter: the line protocol's escaping
(measurement: commas and spaces; tag keys, tag values and field keys: commas, equals
signs and spaces; string field values: double quotes and backslashes), integers with
``i`` and nanosecond timestamps; Prometheus's ``# HELP``/``# TYPE`` lines, metric
names of ``[a-zA-Z_:][a-zA-Z0-9_:]*`` and label values with backslash, double quote
and newline escaped.  Only the read commands offer them (``readings`` in
``device_command``).
"""

from __future__ import annotations

import math
import os
import re
import time

from mbtool.cli.render import Points

# Set by the options as they are parsed, as render's csv_header is.
measurement = "modbus"  # --measurement
device = ""  # the profile's name (-P), a tag and a label when given
textfile = ""  # --textfile PATH: the Prometheus text goes there, atomically


def _values(result) -> list[tuple[dict, object, str]]:
    """Each value with what names it: (labels, value, help) for both formats."""
    if isinstance(result, Points):
        out = []
        for row in result.rows:
            number = row.value if row.number is None else row.number  # text stays text
            about = (row.description or row.name) + (f" ({row.unit})" if row.unit else "") + f", {row.ref}"
            out.append(({"name": row.name, "ref": row.ref}, number, about))
        return out
    table = result.table
    refs = result.refs or [None] * len(result.values)
    out = []
    for ref, address, value in zip(refs, result.addresses, result.values, strict=True):
        labels = {"table": table, "address": str(address)} | ({"ref": ref} if ref else {})
        if isinstance(value, dict):  # --order all: one value an order
            out += [(labels | {"order": order}, each, "") for order, each in value.items()]
        else:
            out.append((labels, value, ""))
    return out


# --- InfluxDB line protocol ------------------------------------------------------------------


def _escape(text: str, specials: str) -> str:
    text = text.replace("\\", "\\\\") if "\\" in specials else text
    for char in specials.replace("\\", ""):
        text = text.replace(char, "\\" + char)
    return text


def _field_value(value) -> str | None:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return f"{value}i"
    if isinstance(value, float):
        return repr(value) if math.isfinite(value) else None  # the protocol has no NaN
    return '"' + _escape(str(value), '\\"') + '"'


def influx_line(result, when: float | None = None) -> str:
    """One line a poll: tags for the unit (and table, device), a field a value."""
    tags = {"unit": str(result.unit)}
    if not isinstance(result, Points):
        tags["table"] = result.table
    if device:
        tags["device"] = device
    fields = []
    for labels, value, _ in _values(result):
        if isinstance(result, Points):
            key = labels["name"]
        else:
            key = labels.get("ref", labels["address"]) + (f"_{labels['order']}" if "order" in labels else "")
        shown = _field_value(value)
        if shown is not None:
            fields.append(f"{_escape(key, ',= ')}={shown}")
    head = _escape(measurement, ", ") + "".join(
        f",{_escape(k, ',= ')}={_escape(v, ',= ')}" for k, v in sorted(tags.items()) if v
    )
    stamp = time.time_ns() if when is None else int(when * 1_000_000_000)
    return f"{head} {','.join(fields)} {stamp}\n"


# --- Prometheus text exposition --------------------------------------------------------------


def _metric_name(name: str) -> str:
    name = re.sub(r"[^a-zA-Z0-9_:]", "_", name)
    return name if re.match(r"[a-zA-Z_:]", name) else "_" + name


def _label_value(text: str) -> str:
    return text.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n")


def _sample_value(value) -> str | None:
    if isinstance(value, bool):
        return "1" if value else "0"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        return (
            "NaN"
            if math.isnan(value)
            else ("+Inf" if value > 0 else "-Inf")
            if math.isinf(value)
            else repr(value)
        )
    return None  # text is no gauge


def prom_text(result) -> str:
    """The exposition of one read: modbus_value{unit,table,address} for registers and bits,
    modbus_NAME{unit,ref} for a map's points (HELP with the description and unit)."""
    base = {"unit": str(result.unit)} | ({"device": device} if device else {})
    metrics: dict[str, tuple[str, list[str]]] = {}
    for labels, value, about in _values(result):
        shown = _sample_value(value)
        if shown is None:
            continue
        if isinstance(result, Points):
            name = _metric_name(f"{measurement}_{labels['name']}")
            labels = {"ref": labels["ref"]}
            help_text = about or "a register map's point, read by mbtool"
        else:
            name = _metric_name(f"{measurement}_value")
            help_text = "Modbus coils, discrete inputs and registers read by mbtool (bits as 0 and 1)"
        pairs = ",".join(f'{k}="{_label_value(v)}"' for k, v in (base | labels).items())
        metrics.setdefault(name, (help_text, []))[1].append(f"{name}{{{pairs}}} {shown}")
    out = []
    for name, (help_text, samples) in metrics.items():
        escaped = help_text.replace("\\", "\\\\").replace("\n", "\\n")
        out += [f"# HELP {name} {escaped}", f"# TYPE {name} gauge", *samples]
    return "\n".join(out) + "\n"


def write_textfile(text: str, path: str) -> None:
    """Atomically: a temporary file in the same directory, then a rename over the old one,
    so node_exporter's textfile collector never reads half a file."""
    from mbtool.errors import OutputFailed

    folder = os.path.dirname(os.path.abspath(path))
    temporary = os.path.join(folder, f".{os.path.basename(path)}.{os.getpid()}.tmp")
    try:
        with open(temporary, "w", encoding="utf-8") as out:
            out.write(text)
        os.replace(temporary, path)
    except OSError as error:
        try:
            os.unlink(temporary)
        except OSError:
            pass
        raise OutputFailed(path, error) from None


def emit(result, fmt: str, out, when: float | None = None) -> None:
    """One read in a monitoring format: to ``out``, or with --textfile to that file."""
    if fmt == "influx":
        out.write(influx_line(result, when))
    elif textfile:
        write_textfile(prom_text(result), textfile)
    else:
        out.write(prom_text(result))
