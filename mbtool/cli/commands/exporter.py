"""``mbtool exporter``: a Prometheus exporter, on prometheus_client (the library Prometheus
documents for exporters in Python), in two modes that one process may serve together.

* Multi-target, ``GET /modbus?target=tcp://192.0.2.10:502&module=NAME&unit=1``: the register
  map NAME (``--maps DIR``, or a map an inventory device names) is read from the target on
  each scrape, as ``read -m`` reads it (MapReader through link.connection.open_client),
  within the deadline the scraper sends in X-Prometheus-Scrape-Timeout-Seconds.  A device
  that fails is HTTP 200 with modbus_up 0 and the reason on modbus_error_info: Prometheus
  keeps why (modbus_exporter answered 500 to every fault, its issue 69, and only said the
  scrape failed).  A target that no ``--allow-target`` pattern allows, and that is no link of
  the inventory, is refused (403) with nothing opened: an exporter on a network must not be
  a way to reach any address.  A link the inventory polls is refused (409): its values are
  on /metrics, and a second master would overlap the plant's requests.
* Inventory, ``mbtool exporter PLANT.toml``: the plant is polled as ``poll`` polls it
  (plant.schedule), and /metrics serves every device's latest values from memory: scrapes
  never touch a bus, answer at once however slow the devices are, and several Prometheus
  servers may scrape at once.

A scrape of /modbus is a fresh prometheus_client registry holding that read's families;
/metrics carries the exporter's own process metrics (prometheus_client's default registry)
after the plant's text, which is poll's, kept ready (PlantMetrics).  This module alone
imports prometheus_client: a one-shot read never loads it.
"""

from __future__ import annotations

import math
import os
import socket
import stat
import sys
import threading
import time
from collections import OrderedDict
from contextlib import contextmanager
from fnmatch import fnmatchcase
from pathlib import Path, PurePath
from urllib.parse import parse_qs

import click

from mbtool.cli.log import log_format_option, run_log_format
from mbtool.cli.notify import systemd_notifier
from mbtool.cli.options import LINK_OPTIONS, with_options
from mbtool.cli.param_types import FilePath, shard_option
from mbtool.cli.plant_text import (
    LAST_SUCCESS,
    UP,
    PlantMetrics,
    check_budgets,
    device_stats,
    link_stats,
    point_metric,
    point_name_clash,
    refuse_point_names,
)
from mbtool.cli.sinks import PLANT, formats
from mbtool.cli.sinks.prom import warn_counter_names
from mbtool.codec.record import replace
from mbtool.errors import KNOWN_ERRORS, ConnectionFailed, NoResponse, PartialRead, UsageError, link_failure
from mbtool.library import find_named
from mbtool.link.base import host_text
from mbtool.link.connection import Connection, check, open_client
from mbtool.link.managed import Backoff, ManagedLink
from mbtool.link.stats import Stats, outcome_of
from mbtool.link.transport import BRIDGE_SCHEMES, NETWORK_SCHEMES, Target, parse_target
from mbtool.plant.inventory import load_inventory, shard
from mbtool.plant.schedule import Plant
from mbtool.plant.stats import PollStats
from mbtool.registermap.load import MapError, load_map
from mbtool.registermap.plan import MapReader
from mbtool.words import counted

# 9502: no port of Prometheus's default port allocations is mbtool's (modbus_exporter has
# 9602, so the two can run on one host); loopback unless the user types another address.
DEFAULT_LISTEN = "127.0.0.1:9502"
DEADLINE_HEADER = "X-Prometheus-Scrape-Timeout-Seconds"
DEFAULT_SCRAPE_TIMEOUT = 10.0  # Prometheus's own default, for a scraper that sends no deadline
# The longest a scrape may read, whatever the scraper sends: a map of a slow serial bus takes
# seconds, not minutes, and a wait has to fit the clocks' arithmetic (9.3e9 s overflowed it).
MAX_SCRAPE_TIMEOUT = 300.0
# Taken from the scraper's deadline for answering (rendering and sending take milliseconds;
# the rest is for the network): the read ends this much before Prometheus gives up.
DEADLINE_MARGIN = 0.25
# The text format the expositions are in (prometheus_client's generate_latest writes it,
# and poll's Prometheus text is it).
CONTENT_TYPE = "text/plain; version=0.0.4; charset=utf-8"
TEXT = "text/plain; charset=utf-8"


@click.command(
    "exporter",
    context_settings={"help_option_names": ["-h", "--help"]},
    short_help="Serve Prometheus: a plant's latest values from memory, or a register map read "
    "from a target on each scrape.",
)
@click.argument("inventory", required=False, type=FilePath(dir_okay=False))
@log_format_option
@click.option(
    "--listen",
    metavar="HOST:PORT",
    default=DEFAULT_LISTEN,
    show_default=True,
    help="Where to serve HTTP; PORT 0 picks a free one. Only loopback by default: another "
    "address (0.0.0.0:9502, [::]:9502) exposes the exporter to the network and is a choice "
    "you type.",
)
@click.option(
    "--maps",
    metavar="DIR",
    type=FilePath(exists=True, file_okay=False),
    help="/modbus: the register maps a scrape's module names, DIR/NAME.toml or DIR/NAME.csv "
    "(before the inventory's maps, each named by its file name without .toml or .csv, and "
    "mbtool's library).",
)
@click.option(
    "--allow-target",
    "allowed",
    metavar="PATTERN",
    multiple=True,
    help="/modbus: a target a scrape may read, as a shell pattern over the target normalised "
    "(port given, an IP address in its usual form), such as 'tcp://192.0.2.1[0-9]:502' (* "
    "matches dots too) (repeatable). A serial device needs a pattern that starts with its path; "
    "pyserial's URL handlers are never opened. The inventory's links are allowed; any other "
    "target is refused with nothing opened.",
)
@shard_option
@with_options(LINK_OPTIONS[:2])  # -t/--timeout and --retries, as every command that reads has them
def exporter(inventory, listen, maps, allowed, shard_part, timeout, retries):
    """A Prometheus exporter. With PLANT.toml it polls the plant as poll does (the same
    inventory and scheduler), and /metrics serves every device's latest values from
    memory, so scrapes never touch a bus: a gauge a point (labels device and the device's
    tags), modbus_up, modbus_last_success_timestamp_seconds, and each device's and link's
    transactions by outcome, exceptions by code, retries that recovered and the
    round-trip time as a histogram (modbus_request_duration_seconds).

    With --maps DIR and --allow-target, GET /modbus?target=TARGET&module=NAME&unit=N reads
    the map NAME from TARGET on each scrape, within the deadline Prometheus sends
    (X-Prometheus-Scrape-Timeout-Seconds, less a quarter of a second). A device that fails
    is HTTP 200 with modbus_up 0 and modbus_error_info{kind,reason}; a target not allowed is
    403, a link the inventory polls 409 (scrape /metrics), a bad request 400, each one line,
    with nothing opened. --timeout and --retries are
    for those reads, never past the deadline; an inventory link's target keeps the link's own.

    /metrics also has the exporter's process metrics. Ctrl-C or SIGTERM stops it with exit
    status 0; 2 for bad options or inventory, 6 when it cannot listen.
    """
    host, port, family = parse_listen(listen)
    plant = None
    if inventory is not None:
        plant = load_inventory(inventory, formats(PLANT))
        if shard_part is not None:  # the other shards' links are no links of this exporter's
            plant = shard(plant, *shard_part)
        check_budgets(plant, False, run_log_format())
    elif shard_part is not None:
        raise UsageError("--shard splits an inventory's links: give the inventory (PLANT.toml)")
    if plant is None and maps is None:
        raise UsageError(
            "nothing to export: give an inventory (PLANT.toml) for /metrics, or --maps DIR and "
            "--allow-target PATTERN for /modbus"
        )
    if plant is None and not allowed:
        raise UsageError(
            "--maps reads maps from the targets --allow-target allows: give a pattern, such as "
            "--allow-target 'tcp://192.0.2.*:502'"
        )
    if plant is not None:
        check_plant_names(plant)
    links = {} if plant is None else plant.links
    scraper = None
    if maps or (plant is not None and plant.maps):
        modules = Modules(Path(maps) if maps else None, {} if plant is None else plant.maps)
        polled = {} if plant is None else {device.link for device in plant.devices}
        scraper = TargetScraper(modules, allowed, links, timeout, retries, polled)
    runner = metrics = None
    if plant is not None:
        metrics = PlantMetrics(plant.labels, run_log_format())
        runner = Plant(plant.links, plant.devices, metrics.report)
        metrics.watch(runner)
    server = open_server(host, port, family, Exporter(metrics, scraper))
    notifier = systemd_notifier()  # systemd's Type=notify: ready once it listens, the watchdog fed
    try:
        # Inside: a SIGTERM as soon as the line is read (a supervisor) is a clean stop too.
        line = _serving_line(server, plant, maps, allowed)
        click.echo(line)
        sys.stdout.flush()
        if notifier:
            notifier.ready(line, None if runner is None else runner.moved)
        if runner is None:
            server.serve_forever(poll_interval=0.5)
        else:
            thread = threading.Thread(target=server.serve_forever, name="http", daemon=True)
            thread.start()
            try:
                runner.run()
            finally:
                server.shutdown()
    except KeyboardInterrupt:
        pass  # Ctrl-C and SIGTERM (cli.main makes it one) stop a service: exit 0
    finally:
        if notifier:
            notifier.stopping()
        server.server_close()


def _serving_line(server, plant, maps, allowed) -> str:
    """The first line: where it serves, and what each path serves."""
    host, port = server.server_address[:2]
    where = host_text(host)
    if plant is not None:
        links = {device.link for device in plant.devices}
        parts = [
            f"/metrics: {counted(len(plant.devices), 'device')} of {plant.path} on {counted(len(links), 'link')}"
        ]
    else:
        parts = ["/metrics: the exporter's process"]
    sources = ([f"maps in {maps}"] if maps else []) + (
        ["the inventory's maps"] if plant and plant.maps else []
    )
    if sources:
        targets = [*allowed, *(["the inventory's links"] if plant is not None else [])]
        parts.append(f"/modbus: {' and '.join(sources)}, targets {', '.join(targets)}")
    return f"exporting on http://{where}:{port} ({'; '.join(parts)})"


def parse_listen(text: str) -> tuple[str, int, socket.AddressFamily]:
    """--listen HOST:PORT: the host (an IPv6 address in brackets) and port; UsageError if not."""
    usage = f"--listen {text}: expected HOST:PORT, such as 127.0.0.1:9502 (0.0.0.0:9502 for every interface)"
    host, colon, port_text = text.rpartition(":")
    if not colon or not host:
        raise UsageError(usage)
    family = socket.AF_INET
    if host.startswith("[") and host.endswith("]"):
        host, family = host[1:-1], socket.AF_INET6
    elif ":" in host:
        raise UsageError(f"--listen {text}: an IPv6 address goes in brackets, such as [::1]:9502")
    if not (port_text.isascii() and port_text.isdigit() and len(port_text) <= 5 and int(port_text) <= 65535):
        raise UsageError(f"--listen {text}: the port is a number, 0..65535")
    return host, int(port_text), family


# --- names: a point's metric must not be one of the exporter's own ---------------------------

# /modbus: the families of a scrape besides the points'.
SCRAPE_NAMES = ("modbus_up", "modbus_error_info", "modbus_scrape_duration_seconds")


def check_plant_names(plant) -> None:
    """Refuse, before anything is opened, an inventory whose map points would be named as
    the exporter's own metrics: a device's (as poll's) and the statistics'."""
    own = {UP, LAST_SUCCESS}
    for name, _, samples in device_stats("", PollStats()) + link_stats("", Stats(), False, 0):
        own.add(name)  # and its samples' names: a histogram's _bucket, _sum and _count
        own.update(line.partition("{")[0] for line in samples.splitlines())
    refuse_point_names(plant, own, "the exporter")


# --- multi-target: a map read from a target on each scrape ----------------------------------


def _shown(text: str) -> str:
    """Text from a request, in a one-line answer: as it is, or quoted when it holds a
    control character (a %0A in the query must not make the answer two lines)."""
    return text if text.isprintable() else repr(text)


class Refused(Exception):
    """A scrape that is not read: the HTTP status and the one line that says why."""

    def __init__(self, status: int, text: str) -> None:
        super().__init__(text)
        self.status = status


class Modules:
    """The register maps a scrape may name: --maps DIR/NAME.toml or .csv, then the maps of
    the inventory's devices, each named by its file name without the extension, then the
    user's maps and mbtool's library (mbtool.library, as -m finds them).  A map is
    loaded once and again when its file changes."""

    def __init__(self, folder: Path | None, inventory_maps: dict[str, str]) -> None:
        self.folder = folder
        self.named: dict[str, list[Path]] = {}
        for path in inventory_maps.values():
            paths = self.named.setdefault(Path(path).stem, [])
            if Path(path).resolve() not in [p.resolve() for p in paths]:
                paths.append(Path(path))
        self.lock = threading.Lock()
        self.loaded: dict[Path, tuple[tuple[int, int], object]] = {}

    def path_of(self, name: str) -> Path:
        if not name or "/" in name or "\\" in name or ".." in name or not name.isprintable():
            raise Refused(400, f"module {name!r}: a map's name, without a folder (no / nor ..)")
        if self.folder is not None:
            for suffix in (".toml", ".csv"):
                path = self.folder / (name + suffix)
                if path.is_file():
                    return path
        paths = self.named.get(name, [])
        if len(paths) > 1:
            raise Refused(
                400, f"module {name}: the inventory has two maps of that name: {paths[0]}, {paths[1]}"
            )
        if paths:
            return paths[0]
        found = find_named(name)  # the user's maps, then mbtool's library: as -m finds them
        if found is not None:
            return found
        where = [f"{self.folder} has no {name}.toml nor {name}.csv"] if self.folder is not None else []
        if self.named:
            where.append(f"the inventory's maps are {', '.join(sorted(self.named))}")
        where.append("mbtool's library has none (mbtool maps list)")
        raise Refused(400, f"no module {name}: {'; '.join(where)}")

    def load(self, path: Path):
        """The map at ``path``, its points checked against the scrape's own names; MapError if
        it cannot be used."""
        try:
            info = path.stat()
            stamp = (info.st_mtime_ns, info.st_size)
        except OSError as error:
            raise MapError(f"cannot read map {path}: {error.strerror or error}") from None
        with self.lock:
            kept = self.loaded.get(path)
        if kept is not None and kept[0] == stamp:
            return kept[1]
        register_map = load_map(path)
        clash = point_name_clash(register_map.points.values(), set(SCRAPE_NAMES), "the exporter")
        if clash:
            raise MapError(f"{path}: {clash}")
        warn_counter_names(register_map.points.values(), where=f"{path}: ")
        with self.lock:
            self.loaded[path] = (stamp, register_map)
        return register_map


class TargetScraper:
    """/modbus: a target's map read on each scrape, one scrape of a target at a time (a bus
    has one master, and many devices take one connection)."""

    def __init__(
        self, modules: Modules, patterns, links: dict, timeout: float, retries: int, polled=()
    ) -> None:
        """``links``: the inventory's, by name; ``polled``: the names of those its plant polls."""
        self.modules = modules
        self.patterns = allow_patterns(patterns)
        # The inventory's links by their targets' keys (link_key): another spelling is one link.
        self.links = {link_key(parse_target(link.connection.port)): link for link in links.values()}
        self.polled = {key for key, link in self.links.items() if link.name in polled}
        self.timeout = timeout
        self.retries = retries
        self.locks = TargetLocks()

    def scrape(self, query: str, deadline_header: str | None) -> tuple[int, str, bytes]:
        """(HTTP status, content type, body) of one scrape."""
        started = time.monotonic()
        budget = scrape_budget(deadline_header)
        try:
            where, module, unit = self._asked(query)
            connection = self._connection(where, unit)
            path = self.modules.path_of(module)
        except Refused as refusal:
            return refusal.status, TEXT, f"{refusal}\n".encode()

        try:
            register_map = self.modules.load(path)
        except KNOWN_ERRORS as error:  # the exporter's configuration, not the device: 500
            return 500, TEXT, f"module {module}: {error}\n".encode()
        readings, problem, kind = self._read(where, connection, register_map, started + budget, budget)
        from prometheus_client import (  # noqa: PLC0415 - 32 ms: not for mbtool --help
            CollectorRegistry,
            generate_latest,
        )

        registry = CollectorRegistry()
        registry.register(_ScrapeCollector(str(unit), readings, problem, kind, time.monotonic() - started))
        return 200, CONTENT_TYPE, generate_latest(registry)

    def _asked(self, query: str) -> tuple[Target, str, int]:
        try:
            params = parse_qs(query, keep_blank_values=True, strict_parsing=bool(query), max_num_fields=16)
        except ValueError as error:
            raise Refused(400, f"the query {query!r} cannot be read: {error}") from None
        for name, values in params.items():
            if len(values) > 1:
                raise Refused(400, f"{_shown(name)} is given {len(values)} times: give it once")
        for name in ("target", "module"):
            if not params.get(name, [""])[0]:
                raise Refused(400, f"no {name}: /modbus?target=tcp://192.0.2.10:502&module=NAME&unit=1")
        target, module = params["target"][0], params["module"][0]
        unit_text = params.get("unit", ["1"])[0]
        if not (
            unit_text.isascii() and unit_text.isdigit() and len(unit_text) <= 3 and int(unit_text) <= 255
        ):
            raise Refused(400, f"unit {unit_text!r}: a unit id is a number, 0..255")
        return self._allowed(target), module, int(unit_text)

    def _allowed(self, text: str) -> Target:
        """The target a scrape names, parsed and normalised, if it may be opened; Refused if
        not (400: it names no target; 403: it is not allowed), with nothing opened."""
        try:
            where = parse_target(text).normalised()
        except UsageError as error:
            raise Refused(400, f"target {_shown(text)}: {_shown(str(error))}") from None
        key = link_key(where)
        if key in self.polled:
            # A second master beside the plant's on a TCP link (the device answers two at once,
            # or not), "port busy" on a serial one, the exporter itself holding it: the plant's
            # values are in /metrics already.
            raise Refused(
                409, f"link {self.links[key].name} is polled by this exporter's inventory: scrape /metrics"
            )
        if key in self.links:
            return where
        if where.handler and where.handler not in BRIDGE_SCHEMES:
            raise Refused(
                403,
                f"target {_shown(text)} is a pyserial URL handler ({where.handler}://), which a "
                "scrape never opens: network links and serial devices only",
            )
        if not any(_stands_for(pattern, where) for pattern in self.patterns):
            raise Refused(
                403,
                f"target {_shown(text)} is not allowed: no --allow-target pattern matches it"
                + (", and it is no link of the inventory" if self.links else ""),
            )
        if where.scheme == "serial" and not where.handler:
            why = _not_a_serial_device(where.path)
            if why:
                raise Refused(403, f"target {_shown(text)} is not allowed: {why}")
        return where

    def _connection(self, where: Target, unit: int):
        link = self.links.get(link_key(where))
        base = (
            link.connection
            if link is not None
            else Connection(str(where), timeout=self.timeout, retries=self.retries)
        )
        connection = replace(base, unit=unit)
        try:
            check(connection, "a scrape's read")
        except UsageError as error:
            raise Refused(400, f"target {_shown(str(where))}: {_shown(str(error))}") from None
        return connection

    def _read(self, where: Target, connection, register_map, deadline: float, budget: float):
        """(readings or None, the error or None, its kind) of the map read within ``deadline``."""
        with self.locks.held(link_key(where), deadline) as turn:
            if not turn:
                busy = NoResponse(
                    f"another scrape of {where} held it past this scrape's deadline ({budget:g} s)"
                )
                return None, busy, "busy"
            return _read_map(connection, register_map, deadline, budget)


# Targets whose lock is kept: far more than are scraped at once (MAX_CONNECTIONS), so a lock in
# use always stays, and few enough that scrapes of ever new targets cost no memory.
LOCKS_KEPT = 1024


class TargetLocks:
    """One lock a link (by link_key), the LOCKS_KEPT used last kept: a lock that a scrape holds
    or waits on is never dropped, or a second scrape would get a fresh one and read at once."""

    def __init__(self) -> None:
        self.guard = threading.Lock()
        self.locks: OrderedDict[tuple, list] = OrderedDict()  # key -> [its lock, scrapes using it]

    def __len__(self) -> int:
        return len(self.locks)

    @contextmanager
    def held(self, key: tuple, deadline: float):
        """Yield whether the link's lock was taken before ``deadline`` (monotonic)."""
        with self.guard:
            entry = self.locks.get(key) or [threading.Lock(), 0]
            entry[1] += 1
            self.locks[key] = entry
            self.locks.move_to_end(key)
            if len(self.locks) > LOCKS_KEPT:
                idle = next((k for k, (_, users) in self.locks.items() if not users), None)
                if idle is not None:
                    del self.locks[idle]
        lock = entry[0]
        taken = lock.acquire(timeout=max(0.0, deadline - time.monotonic()))
        try:
            yield taken
        finally:
            if taken:
                lock.release()
            with self.guard:
                entry[1] -= 1


# --- what a scrape may open ------------------------------------------------------------------

WILDCARDS = "*?["


def allow_patterns(patterns) -> tuple[str, ...]:
    """--allow-target's patterns as they are matched: the scheme in lower case, and a pattern
    without a wildcard read as the target it names, normalised (tcp://192.0.2.10 allows
    tcp://192.0.2.10:502 and its other spellings); UsageError (exit 2) if it names none."""
    out = []
    for pattern in patterns:
        scheme, sep, rest = pattern.partition("://")
        if sep and not any(c in scheme for c in WILDCARDS):
            pattern = f"{scheme.lower()}://{rest}"
        if not any(c in pattern for c in WILDCARDS):
            try:
                pattern = str(parse_target(pattern).normalised())
            except UsageError as error:
                raise UsageError(f"--allow-target {pattern}: {error}") from None
        out.append(pattern)
    return tuple(out)


def _stands_for(pattern: str, where: Target) -> bool:
    """Whether ``pattern`` allows ``where`` (normalised).  A network link (and socket://, its
    serial frames over TCP) by any pattern that matches it; rfc2217://, sim:// and a serial
    device only by a pattern that names them, its scheme or its first character typed:
    '*:5020' stands for network links, never for a device or a remote serial port."""
    text = str(where)
    if not fnmatchcase(text, pattern):
        return False
    if where.scheme in NETWORK_SCHEMES or where.handler == "socket":
        return True
    if where.scheme == "serial" and not where.handler:  # a device path
        return "://" not in pattern and pattern[:1] not in ("", *WILDCARDS)
    scheme = where.handler or where.scheme
    return pattern.lower().startswith(f"{scheme}://")


def _not_a_serial_device(path: str) -> str:
    """Why a device path is no serial device a scrape may open ("" if it may be): a path
    with .., or one that resolves (symbolic links followed) to anything but a character
    device under /dev.  A device that is not there is opened, and says so (modbus_up 0)."""
    if ".." in PurePath(path).parts:
        return "a device's path has no .. in it"
    if os.name != "posix":
        return ""  # COM3: no /dev to resolve into
    real = os.path.realpath(path)
    try:
        mode = os.stat(real).st_mode
    except OSError:
        mode = None
    if not real.startswith("/dev/") or (mode is not None and not stat.S_ISCHR(mode)):
        return f"it is no serial device (it resolves to {_shown(real)})"
    return ""


def link_key(where: Target) -> tuple:
    """One link's key, whatever its spelling (Target.endpoint)."""
    return where.endpoint()


def scrape_budget(header: str | None) -> float:
    """Seconds the read may take: the scraper's deadline (at most MAX_SCRAPE_TIMEOUT) less a
    margin for the answer."""
    try:
        seconds = float(header) if header else DEFAULT_SCRAPE_TIMEOUT
    except ValueError:
        seconds = DEFAULT_SCRAPE_TIMEOUT
    if not 0 < seconds < math.inf:
        seconds = DEFAULT_SCRAPE_TIMEOUT
    seconds = min(seconds, MAX_SCRAPE_TIMEOUT)
    return max(seconds - DEADLINE_MARGIN, seconds / 2)


def _read_map(connection, register_map, deadline: float, budget: float):
    """A map read over a link of its own, as read -m reads it; each reply awaited no longer
    than the deadline leaves, and no retry past it."""
    left = deadline - time.monotonic()
    if left <= 0:
        return (
            None,
            NoResponse(f"the scrape's deadline ({budget:g} s) passed before the read began"),
            "timeout",
        )
    timeout, retries, unit = connection.timeout, connection.retries, connection.unit
    link = ManagedLink(lambda: open_client(replace(connection, timeout=min(timeout, left))), Backoff(0.0))
    try:
        client = link.open()
    except (*KNOWN_ERRORS, OSError) as error:  # an OSError is the ConnectionFailed it means
        return None, error, outcome_of(error)

    def execute(request):
        left = deadline - time.monotonic()
        if left <= 0:
            raise NoResponse(f"the scrape's deadline ({budget:g} s) passed before the read ended")
        client.timeout = min(timeout, math.floor(left * 1000) / 1000 or left)  # "within 0.747 s"
        client.retries = min(retries, max(0, int(left / client.timeout) - 1))
        return link.execute(unit, request)

    try:
        return MapReader(register_map.points.values(), register_map.max_gap).read(execute), None, ""
    except PartialRead as partial:
        return partial.readings, partial, "partial"
    except (*KNOWN_ERRORS, OSError) as failure:
        lost = link_failure(failure)
        return None, lost, outcome_of(lost)
    finally:
        link.close()


class _ScrapeCollector:
    """One scrape's families: modbus_up, why it failed, how long it took, a gauge a point."""

    def __init__(self, unit: str, readings, error, kind: str, seconds: float) -> None:
        self.unit, self.readings, self.error, self.kind, self.seconds = unit, readings, error, kind, seconds

    def collect(self):
        from prometheus_client.core import (  # noqa: PLC0415 - 32 ms: not for mbtool --help
            GaugeMetricFamily,
            InfoMetricFamily,
        )

        up = GaugeMetricFamily(
            "modbus_up",
            "1 when the device answered the scrape's read, 0 when it could not be read (no value is shown then)",
            labels=["unit"],
        )
        up.add_metric([self.unit], int(self.readings is not None))
        yield up
        if self.error is not None:
            error = InfoMetricFamily(
                "modbus_error",
                "Why the read failed, in whole or in part: kind is timeout, exception, corrupt, "
                "not_ours, link_lost, connection, busy or partial; reason the error's own line",
                labels=["unit"],
            )
            error.add_metric([self.unit], {"kind": self.kind, "reason": str(self.error)})
            yield error
        duration = GaugeMetricFamily(
            "modbus_scrape_duration_seconds", "Seconds the scrape took, the read included", labels=["unit"]
        )
        duration.add_metric([self.unit], self.seconds)
        yield duration
        families: dict[str, GaugeMetricFamily] = {}
        for reading in self.readings or ():
            metric = point_metric(reading)
            if metric is None:
                continue
            name, about, number = metric
            if name not in families:
                families[name] = GaugeMetricFamily(name, about, labels=["unit", "ref"])
            families[name].add_metric([self.unit, reading.point.ref], number)
        yield from families.values()


# --- HTTP ------------------------------------------------------------------------------------


class Exporter:
    """What the HTTP handlers answer: /metrics, /modbus and a page that names them."""

    def __init__(self, plant: PlantMetrics | None, scraper: TargetScraper | None) -> None:
        self.plant = plant
        self.scraper = scraper

    def answer(self, path: str, query: str, deadline_header: str | None) -> tuple[int, str, bytes]:
        if path == "/metrics":
            from prometheus_client import (  # noqa: PLC0415 - 32 ms: not for mbtool --help
                REGISTRY,
                generate_latest,
            )

            text = self.plant.text() if self.plant is not None else b""
            return 200, CONTENT_TYPE, text + generate_latest(REGISTRY)
        if path == "/modbus":
            if self.scraper is None:
                return 404, TEXT, b"/modbus reads register maps: start the exporter with --maps DIR\n"
            return self.scraper.scrape(query, deadline_header)
        if path == "/":
            lines = ["mbtool exporter", "/metrics: the plant's latest values and the exporter's process"]
            if self.scraper is not None:
                lines.append("/modbus?target=TARGET&module=NAME&unit=N: a map read from a target")
            return 200, TEXT, ("\n".join(lines) + "\n").encode()
        return 404, TEXT, f"no page {path}: /metrics, /modbus\n".encode()


def open_server(host: str, port: int, family, exporter: Exporter):
    """The HTTP server, bound; ConnectionFailed (exit 6) if it cannot be."""
    from mbtool.cli.http_server import HttpServer  # noqa: PLC0415 - h11, selectors: serving only

    def answer(path: str, query: str, headers: dict[str, str]) -> tuple[int, str, bytes]:
        try:
            return exporter.answer(path, query, headers.get(DEADLINE_HEADER.lower()))
        except Exception as error:  # a bug: one line to the scraper and on stderr, never a traceback
            line = f"internal error: {type(error).__name__}: {error}"
            asked = path + (f"?{query}" if query else "")
            print(f"mbtool: {line} (answering {_shown(asked)})", file=sys.stderr, flush=True)
            return 500, TEXT, f"{_shown(line)}\n".encode()

    try:
        return HttpServer(host, port, family, answer)
    except OSError as error:
        raise ConnectionFailed(
            f"cannot listen on {host_text(host)}:{port}: {error.strerror or error}"
        ) from None
