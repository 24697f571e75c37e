"""Output that monitoring systems read as it is: InfluxDB line protocol (``-o influx``)
and the Prometheus text exposition format (``-o prom``, ``--textfile``).

Both follow their system's reference to the letter: the line protocol's escaping
(measurement: commas and spaces; tag keys, tag values and field keys: commas, equals
signs and spaces; backslashes doubled in all of them; string field values: double quotes
and backslashes), names it cannot carry refused before anything is sent (``check_names``;
a map's point names when the map is loaded), a field's type fixed by its point
(``Point.number_of``), integers with ``i`` and nanosecond timestamps; Prometheus's
``# HELP``/``# TYPE`` lines, metric names of ``[a-zA-Z_:][a-zA-Z0-9_:]*`` and label
values with backslash, double quote and newline escaped, and ``modbus_up`` with the time
of the last success in every exposition.  Only the read commands offer them
(``readings`` in ``device_command``).

A run writes them through one ``Metrics``, made from its settings: what it learns as it
goes (when the device last answered, the fields it warned about) is the run's own.
"""

from __future__ import annotations

import math
import os
import re
import stat
import sys
import time

from mbtool.cli.results import Points
from mbtool.cli.settings import Settings
from mbtool.codec.errors import RequestError
from mbtool.errors import ExitCode, OutputFailed, exit_code_for

# The help of the family of raw registers and bits, modbus_value{table,address}.
VALUE_HELP = "Modbus coils, discrete inputs and registers read by mbtool (bits as 0 and 1)"
# The failures that mean the device could not be read: no reply, an exception (to every
# point of a map), a reply that is not one, a link that cannot be opened.
DEVICE_FAILURES = (ExitCode.TIMEOUT, ExitCode.EXCEPTION, ExitCode.INVALID_RESPONSE, ExitCode.CONNECTION)


class Metrics:
    """One run's -o influx or -o prom (--textfile): its measurement, its profile's name, its
    textfile, the unit the status metrics name when no result does; and what the run has
    learnt: when the device last answered, the fields left out of a line so far."""

    def __init__(self, settings: Settings, unit: int) -> None:
        self.fmt = settings.output_format  # influx or prom
        self.measurement = settings.measurement
        self.device = settings.device
        self.textfile = settings.textfile
        self.unit = unit
        self.last_success: float | None = None  # when the device last answered a read (Unix time)
        self.warned: set[str] = set()  # the fields left out so far, each warned about once
        self.swept = False  # the textfile's stale temporaries have been looked for

    def check_names(self) -> None:
        """Refuse, before anything is sent, a measurement or profile name the output cannot
        carry (name_problem).  A map's point names are held to one line when the map is loaded."""
        names = [("--measurement", self.measurement, "a measurement")]
        if self.device:
            names.append(("profile", self.device, "a tag or label"))
        for option, name, what in names:
            problem = name_problem(name, what, influx=self.fmt == "influx")
            if problem:
                raise RequestError(f"{option} {name!r}: {problem}")

    def check_point_names(self, points) -> None:
        """Refuse, before anything is sent, a map point whose metric would be a status metric;
        warn of one named as a counter's."""
        for point in points:
            metric = _metric_name(f"{self.measurement}_{point.name}")
            if metric in self.status_names():
                raise RequestError(
                    f"point {point.name}: its metric, {metric}, is the "
                    "one that says whether the device answered; rename the point or give --measurement"
                )
        warn_counter_names(points, self.measurement)

    def emit(self, result, out, when: float | None = None) -> None:
        """One read: to ``out``, or with --textfile to that file."""
        if self.fmt == "influx":
            out.write(self.influx_line(result, when))
            return
        self.last_success = time.time() if when is None else when
        if self.textfile:
            self._write_textfile(self.prom_text(result))
        else:
            out.write(self.prom_text(result))

    def emit_failure(self, error: BaseException, out) -> None:
        """A read that failed: for Prometheus, an exposition that says the device could not be
        read and when it last answered, in place of the values read before, which a scrape
        would take as current.  The line protocol has no such thing: an InfluxDB line is
        written only for values read."""
        if self.fmt != "prom" or exit_code_for(error) not in DEVICE_FAILURES:
            return  # a bad request (nothing sent), a full disk: no news of the device
        if self.textfile:
            if self.last_success is None:  # a run before this one may have read it: the file says when
                self.last_success = _last_success_in(self.textfile, self.status_names()[1])
            self._write_textfile(self.prom_down_text())
        else:
            out.write(self.prom_down_text())

    def _write_textfile(self, text: str) -> None:
        write_textfile(text, self.textfile, sweep=not self.swept)
        self.swept = True

    # --- InfluxDB line protocol --------------------------------------------------------------

    def influx_line(self, result, when: float | None = None) -> str:
        """One line a poll: tags for the unit (and table, device), a field a value.

        A value the protocol cannot carry (NaN, an infinity) is left out with a warning,
        once a run for each field; a read left with no field writes no line, as a point
        must have one."""
        tags = {"unit": str(result.unit)}
        points = isinstance(result, Points)
        if not points:
            tags["table"] = result.table
        if self.device:
            tags["device"] = self.device
        fields = []
        for labels, value, _ in _values(result):
            if points:
                key = labels["name"]
            else:
                key = labels.get("ref", labels["address"]) + (
                    f"_{labels['order']}" if "order" in labels else ""
                )
            shown = _field_value(value)
            if shown is None:
                self._warn_left_out(f"{key} ({labels['ref']})" if points else f"{result.table} {key}", value)
                continue
            fields.append(f"{_escape(key, KEY_SPECIALS)}={shown}")
        stamp = time.time_ns() if when is None else int(when * 1_000_000_000)
        return influx_text(self.measurement, tags, fields, stamp)

    def _warn_left_out(self, what: str, value: object) -> None:
        if what not in self.warned:
            self.warned.add(what)
            print(
                f"mbtool: warning: {what} reads {value}: left out of the InfluxDB line "
                "(it has no NaN or infinity)",
                file=sys.stderr,
                flush=True,
            )

    # --- Prometheus text exposition ----------------------------------------------------------

    def prom_text(self, result) -> str:
        """The exposition of one read: modbus_value{unit,table,address} for registers and
        bits, modbus_NAME{unit,ref} for a map's points (HELP with the description and unit),
        after modbus_up 1 and when the device last answered (this read)."""
        base = {"unit": str(result.unit)} | ({"device": self.device} if self.device else {})
        metrics = self._status(result.unit, up=True)
        for labels, value, about in _values(result):
            shown = _sample_value(value)
            if shown is None:
                continue
            if isinstance(result, Points):
                name = _metric_name(f"{self.measurement}_{labels['name']}")
                labels = {"ref": labels["ref"]}
                help_text = about or "a register map's point, read by mbtool"
            else:
                name = _metric_name(f"{self.measurement}_value")
                help_text = VALUE_HELP
            metrics.setdefault(name, (help_text, []))[1].append(
                f"{name}{{{_label_pairs(base | labels)}}} {shown}"
            )
        return _exposition(metrics)

    def prom_down_text(self) -> str:
        """The exposition when the device could not be read: modbus_up 0 and when it last
        answered, and no value: one read before would be scraped as current."""
        return _exposition(self._status(self.unit, up=False))

    def status_names(self) -> tuple[str, str]:
        """The status metrics' names: modbus_up, modbus_last_success_timestamp_seconds."""
        return (
            _metric_name(f"{self.measurement}_up"),
            _metric_name(f"{self.measurement}_last_success_timestamp_seconds"),
        )

    def _status(self, unit_id: int, up: bool) -> dict[str, tuple[str, list[str]]]:
        up_name, last_name = self.status_names()
        pairs = _label_pairs({"unit": str(unit_id)} | ({"device": self.device} if self.device else {}))
        metrics = {
            up_name: (
                "1 when the device answered the read, 0 when it could not be read (no value is shown then)",
                [f"{up_name}{{{pairs}}} {int(up)}"],
            )
        }
        if self.last_success is not None:
            metrics[last_name] = (
                "When the device last answered a read, in seconds since the epoch",
                [f"{last_name}{{{pairs}}} {self.last_success!r}"],
            )
        return metrics


def name_problem(name: str, what: str, influx: bool) -> str:
    """Why ``name`` cannot be written; "" when it can (registermap.load.name_problem: the
    inventory's loader checks a device's measurement by it too)."""
    from mbtool.registermap.load import name_problem  # noqa: PLC0415 - the map loader, 4-8 ms: -m only

    return name_problem(name, what, influx)


def _values(result) -> list[tuple[dict, object, str]]:
    """Each value with what names it: (labels, value, help) for both formats."""
    if isinstance(result, Points):
        out = []
        for row in result.rows:
            if row.value is None:
                continue  # no data (the map's invalid key): no field, no sample
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
    """The reference's escaping: a backslash before each special character, and a backslash
    itself doubled (two contiguous backslashes are one), so one at the end of a name never
    escapes the separator after it."""
    text = text.replace("\\", "\\\\")
    for char in specials:
        text = text.replace(char, "\\" + char)
    return text


MEASUREMENT_SPECIALS = ", "  # commas and spaces
KEY_SPECIALS = ",= "  # tag keys, tag values and field keys: commas, equals signs and spaces


def _field_value(value) -> str | None:
    """The value as the line protocol writes it; None for NaN and the infinities, which it
    cannot carry."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return f"{value}i"
    if isinstance(value, float):
        return repr(value) if math.isfinite(value) else None
    return '"' + str(value).replace("\\", "\\\\").replace('"', '\\"') + '"'


# --- Prometheus text exposition --------------------------------------------------------------


def _metric_name(name: str) -> str:
    name = re.sub(r"[^a-zA-Z0-9_:]", "_", name)
    return name if re.match(r"[a-zA-Z_:]", name) else "_" + name


# The ends of a name Prometheus keeps for a counter (_total) and for the series of a histogram
# or a summary: promtool flags a gauge named so, and a reader would take rate() of it.
COUNTER_ENDS = {
    "_total": "counters",
    "_count": "histograms and summaries",
    "_sum": "histograms and summaries",
    "_bucket": "histograms",
}


def warn_counter_names(points, prefix: str = "modbus", where: str = "", warned: set | None = None) -> None:
    """One warning on stderr for each map point whose metric ends as a counter's does
    (_total, _count, _sum, _bucket): a point is a gauge.  ``where``: what names the map
    ("PATH: "); ``warned``: the metrics warned of already (a map several devices share)."""
    warned = set() if warned is None else warned
    for point in points:
        metric = _metric_name(f"{prefix}_{point.name}")
        end = next((end for end in COUNTER_ENDS if metric.endswith(end)), None)
        if end is None or metric in warned:
            continue
        warned.add(metric)
        print(
            f"mbtool: warning: {where}point {point.name}: its metric, {metric}, is a gauge, but Prometheus "
            f"keeps names ending in {end} for {COUNTER_ENDS[end]}; rename the point",
            file=sys.stderr,
            flush=True,
        )


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


def _label_pairs(labels: dict[str, str]) -> str:
    return ",".join(f'{k}="{_label_value(v)}"' for k, v in labels.items())


def _exposition(metrics: dict[str, tuple[str, list[str]]]) -> str:
    out = []
    for name, (help_text, samples) in metrics.items():
        escaped = help_text.replace("\\", "\\\\").replace("\n", "\\n")
        out += [f"# HELP {name} {escaped}", f"# TYPE {name} gauge", *samples]
    return "\n".join(out) + "\n"


def influx_text(measurement: str, tags: dict[str, str], fields: list[str], stamp_ns: int) -> str:
    """One line of the line protocol: the measurement and its tags escaped (sorted, an empty
    one left out), the fields as given (``key=value``, escaped), the time in nanoseconds;
    "" when there is no field, as a line must have one."""
    if not fields:
        return ""
    head = _escape(measurement, MEASUREMENT_SPECIALS) + "".join(
        f",{_escape(k, KEY_SPECIALS)}={_escape(v, KEY_SPECIALS)}" for k, v in sorted(tags.items()) if v
    )
    return f"{head} {','.join(fields)} {stamp_ns}\n"


def write_textfile(text: str, path: str, sweep: bool = True) -> None:
    """Atomically: a temporary file in the same directory, then a rename over the old one,
    so node_exporter's textfile collector never reads half a file.

    The temporary file is tempfile's: created with O_EXCL under a name no one can guess, so
    a symlink planted beside the textfile is never followed, and the rename replaces a
    symlink at PATH itself rather than writing through it.  It is made readable as any file
    the user creates (the umask), as node_exporter runs as another user.  Its name,
    ``.NAME.PID.<8 random characters>.tmp``, says whose it is: one a killed mbtool left behind (SIGKILL
    gives no chance to clean up) is removed at a run's first write (``sweep``)."""
    import tempfile  # noqa: PLC0415 - 3 ms or more: --textfile only

    folder, name = os.path.split(os.path.abspath(path))
    if sweep:
        _remove_stale_temporaries(folder, name)
    temporary = None
    try:
        descriptor, temporary = tempfile.mkstemp(prefix=f".{name}.{os.getpid()}.", suffix=".tmp", dir=folder)
        with open(descriptor, "w", encoding="utf-8") as out:
            os.fchmod(descriptor, 0o666 & ~_umask())
            out.write(text)
        os.replace(temporary, path)
    except OSError as error:
        if temporary is not None:
            try:
                os.unlink(temporary)
            except OSError:
                pass
        raise OutputFailed(path, error) from None


def check_textfile(path: str) -> None:
    """OutputFailed (exit 7) now if write_textfile could not write at ``path``: its temporary
    made in the folder and removed, before a long run polls anything (as dump finds its file)."""
    import tempfile  # noqa: PLC0415 - 3 ms or more: --textfile only

    folder, name = os.path.split(os.path.abspath(path))
    try:
        descriptor, temporary = tempfile.mkstemp(prefix=f".{name}.{os.getpid()}.", suffix=".tmp", dir=folder)
        os.close(descriptor)
        os.unlink(temporary)
    except OSError as error:
        raise OutputFailed(path, error) from None


def _umask() -> int:
    mask = os.umask(0)  # the only way to read it is to set it
    os.umask(mask)
    return mask


def _remove_stale_temporaries(folder: str, name: str) -> None:
    """Remove this textfile's temporaries whose writer is gone: regular files of ours (never
    a symlink's target), named by write_textfile, whose process no longer runs."""
    pattern = re.compile(rf"\.{re.escape(name)}\.(\d+)\.[a-z0-9_]+\.tmp")
    try:
        names = os.listdir(folder)
    except OSError:
        return  # the write itself will say what is wrong with the folder
    for each in names:
        found = pattern.fullmatch(each)
        if found is None or _running(int(found[1])):
            continue
        where = os.path.join(folder, each)
        try:
            info = os.lstat(where)
            if stat.S_ISREG(info.st_mode) and info.st_uid == os.geteuid():
                os.unlink(where)
        except OSError:
            pass  # gone already, or not ours to remove


def _running(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # EPERM: it runs, as another user
        return True
    return True


def _last_success_in(path: str, name: str) -> float | None:
    """The last success a textfile written before tells of (its sample line of ``name``), if any."""
    try:
        with open(path, encoding="utf-8") as old:
            for line in old:
                if line.startswith(name + "{"):
                    return float(line.rsplit(" ", 1)[1])
    except (OSError, ValueError, UnicodeDecodeError):
        pass
    return None
