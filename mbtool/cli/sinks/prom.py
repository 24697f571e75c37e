"""-o prom and --textfile: the Prometheus text exposition format, to the letter: ``# HELP``
and ``# TYPE`` lines, metric names of ``[a-zA-Z_:][a-zA-Z0-9_:]*``, label values with
backslash, double quote and newline escaped, and ``modbus_up`` with the time of the last
success in every exposition; a textfile rewritten whole and atomically, for
node_exporter's textfile collector.

``Readings`` writes a read command's values (read -o prom); the plant's text (poll -o prom,
the exporter's /metrics) is ``cli/plant_text.py``'s, made of the same families.
"""

from __future__ import annotations

import math
import os
import re
import stat
import sys
import time

from mbtool.cli.metrics import ReadingPolls, values_of
from mbtool.cli.metrics import Readings as MonitoringReadings
from mbtool.cli.results import Points
from mbtool.errors import OutputFailed, UsageError

# The help of the family of raw registers and bits, modbus_value{table,address}.
VALUE_HELP = "Modbus coils, discrete inputs and registers read by mbtool (bits as 0 and 1)"


Polls = ReadingPolls  # read --interval: each poll through the run's Readings


class Readings(MonitoringReadings):
    """A read command's -o prom (--textfile): an exposition a read, on stdout or rewritten
    to the textfile; and what the run learnt: when the device last answered."""

    influx = False

    def check(self, points=()) -> None:
        """Refuse, before anything is sent, a map point whose metric would be a status metric;
        warn of one named as a counter's."""
        super().check(points)
        for point in points:
            metric = metric_name(f"{self.measurement}_{point.name}")
            if metric in self.status_names():
                raise UsageError(
                    f"point {point.name}: its metric, {metric}, is the "
                    "one that says whether the device answered; rename the point or give --measurement"
                )
        warn_counter_names(points, self.measurement)

    def emit(self, result, out, when: float | None = None) -> None:
        """One read: to ``out``, or with --textfile to that file."""
        self.last_success = time.time() if when is None else when
        self._write(self.text(result), out)

    def emit_failure(self, error: BaseException, out) -> None:
        """A read that failed: an exposition that says the device could not be read and when
        it last answered, in place of the values read before, which a scrape would take as
        current."""
        if not self.device_failed(error):
            return  # a bad request (nothing sent), a full disk: no news of the device
        if self.textfile and self.last_success is None:
            # a run before this one may have read it: the file says when
            self.last_success = last_success_in(self.textfile, self.status_names()[1])
        self._write(self.down_text(), out)

    def _write(self, text: str, out) -> None:
        if self.textfile:
            write_textfile(text, self.textfile, sweep=not self.swept)
            self.swept = True
        else:
            out.write(text)

    def text(self, result) -> str:
        """The exposition of one read: modbus_value{unit,table,address} for registers and
        bits, modbus_NAME{unit,ref} for a map's points (HELP with the description and unit),
        after modbus_up 1 and when the device last answered (this read)."""
        base = {"unit": str(result.unit)} | ({"device": self.device} if self.device else {})
        metrics = self._status(result.unit, up=True)
        for labels, value, about in values_of(result):
            shown = sample_value(value)
            if shown is None:
                continue
            if isinstance(result, Points):
                name = metric_name(f"{self.measurement}_{labels['name']}")
                labels = {"ref": labels["ref"]}
                help_text = about or "a register map's point, read by mbtool"
            else:
                name = metric_name(f"{self.measurement}_value")
                help_text = VALUE_HELP
            metrics.setdefault(name, (help_text, []))[1].append(
                f"{name}{{{label_pairs(base | labels)}}} {shown}"
            )
        return exposition(metrics)

    def down_text(self) -> str:
        """The exposition when the device could not be read: modbus_up 0 and when it last
        answered, and no value: one read before would be scraped as current."""
        return exposition(self._status(self.unit, up=False))

    def status_names(self) -> tuple[str, str]:
        """The status metrics' names: modbus_up, modbus_last_success_timestamp_seconds."""
        return (
            metric_name(f"{self.measurement}_up"),
            metric_name(f"{self.measurement}_last_success_timestamp_seconds"),
        )

    def _status(self, unit_id: int, up: bool) -> dict[str, tuple[str, list[str]]]:
        up_name, last_name = self.status_names()
        pairs = label_pairs({"unit": str(unit_id)} | ({"device": self.device} if self.device else {}))
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


def metric_name(name: str) -> str:
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
        metric = metric_name(f"{prefix}_{point.name}")
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


def label_value(text: str) -> str:
    return text.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n")


def sample_value(value) -> str | None:
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


def label_pairs(labels: dict[str, str]) -> str:
    return ",".join(f'{k}="{label_value(v)}"' for k, v in labels.items())


# One family of the text format as data, until it is written: its name, its HELP and TYPE lines,
# and its samples, a line each.  A plant's text is kept so (the exporter joins each family's
# samples from every device), never written and cut apart again.
Family = tuple[str, str, str]


def gauges(metrics: dict[str, tuple[str, list[str]]]) -> list[Family]:
    """Gauges: {name: (help, samples)}, a family each."""
    return [family_of(name, "gauge", about, samples) for name, (about, samples) in metrics.items()]


def exposition(metrics: dict[str, tuple[str, list[str]]]) -> str:
    return written(gauges(metrics))


def family_of(name: str, kind: str, about: str, samples) -> Family:
    """One family of the text format: its HELP (backslashes and newlines escaped), its TYPE
    and its samples, a line each.  Every exposition mbtool writes is made of these."""
    about = about.replace("\\", "\\\\").replace("\n", "\\n")
    return (
        name,
        f"# HELP {name} {about}\n# TYPE {name} {kind}\n",
        "".join(f"{sample}\n" for sample in samples),
    )


def family(name: str, kind: str, about: str, samples) -> str:
    """One family, written."""
    return written([family_of(name, kind, about, samples)])


def written(families) -> str:
    """Families in the text format, one after another."""
    return "".join(head + samples for _, head, samples in families)


def le(bound: float) -> str:
    """A bucket's bound as Prometheus writes it (Go's float formatting): 0.001, 1.0, +Inf."""
    return "+Inf" if bound == math.inf else repr(float(bound))


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


def last_success_in(path: str, name: str) -> float | None:
    """The last success a textfile written before tells of (its sample line of ``name``), if any."""
    try:
        with open(path, encoding="utf-8") as old:
            for line in old:
                if line.startswith(name + "{"):
                    return float(line.rsplit(" ", 1)[1])
    except (OSError, ValueError, UnicodeDecodeError):
        pass
    return None


class PlantPolls:
    """poll -o prom: the whole plant's exposition a round, on stdout (cli.plant_text.prom_text,
    written by the plant's output, which also writes --textfile whatever -o says)."""

    measured = False  # --measurement names its measurement
    exposes = True

    def __init__(self, out, csv_header: bool, measurement: str, labels: dict | None = None) -> None:
        self.out = out

    def poll(self, poll, when: str) -> None:
        """A device's poll is in the round's exposition."""

    def event(self, event, when: str) -> None:
        """A change of state shows in modbus_up."""
