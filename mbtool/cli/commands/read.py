"""Read commands: coils, discrete inputs, holding and input registers (FC 01-04), and
``read``, which takes a device manual's references or a register map's point names."""

from __future__ import annotations

import sys
from functools import partial
from operator import attrgetter
from typing import TYPE_CHECKING

import click

from mbtool.cli.options import (
    ORDER_ALL,
    VALUE_TYPES,
    device_command,
    map_option,
    reference_target,
    shared_option,
    type_options_given,
    with_options,
)
from mbtool.cli.param_types import ADDRESS, COUNT, FilePath, Number, PositiveFloat
from mbtool.cli.results import PointFailure, PointRow, Points, PollsOfRead, Result
from mbtool.cli.session import execute, open_client, show, trace_for
from mbtool.cli.settings import Settings
from mbtool.cli.sinks import READINGS, default_format, formats, sink
from mbtool.cli.sinks.json import to_json
from mbtool.codec.data_access import ReadCoils, ReadDiscreteInputs, ReadHoldingRegisters, ReadInputRegisters
from mbtool.codec.record import replace
from mbtool.codec.values import ORDERS, TYPES, registers_needed, value_addresses, value_decoder
from mbtool.errors import PartialRead, UsageError, Verdict
from mbtool.link.connection import Connection

if TYPE_CHECKING:
    from mbtool.cli.broker import PublishedPolls
    from mbtool.cli.poll_output import ChangesOnly, Output

POLL_HELP = """

    \b
    Polling: --interval SECONDS repeats the read over one link until interrupted
    (with --polls N, N times); --polls alone polls every 1 s. Each poll is stamped
    with the time its request went out; a failed poll (a link that cannot be opened,
    the first poll's too) is reported on stderr and polling goes on. At the
    end a summary line goes to stderr; exit 0 if every poll got its reply, else the
    code of the last failure (130 only if interrupted before any poll finished).
    With --changes the first poll is printed whole and later ones only as the values
    that changed: TIME holding 5: 5 -> 99 (a change log for a file).
    """


# Made once and shared by the read commands (options.shared_option): a one-shot read imports
# them all.
POLLING_OPTIONS = [
    shared_option(
        "--interval",
        type=PositiveFloat(zero_ok=True),
        help="Poll every SECONDS over one open link (until interrupted unless --polls); "
        "0 polls back to back.",
    ),
    shared_option(
        "--polls",
        type=Number(0, 10**9, "polls"),
        help="Poll N times (0: until interrupted); interval 1 s unless --interval.",
    ),
    shared_option(
        "--mqtt",
        metavar="URL",
        help="Polling: publish each poll to the MQTT broker at URL (mqtt://HOST[:PORT], "
        "mqtts://HOST[:PORT]) too, one JSON message a poll on mbtool/HOST/NAME, its availability "
        "on .../status (docs/mqtt.md).",
    ),
    shared_option(
        "--name",
        metavar="NAME",
        help="--mqtt: the device's name on the broker (its topic mbtool/HOST/NAME). Default: unit<N>.",
    ),
    shared_option(
        "--stats",
        type=click.Choice(["line", "json"]),
        default="line",
        show_default=True,
        help="Polling: the summary on exit as its line on stderr, or also as one JSON object "
        "(polls, latency, every transaction's outcome, the round-trip histogram) before it.",
    ),
    shared_option(
        "--textfile",
        metavar="PATH",
        type=FilePath(dir_okay=False),
        help="Write the Prometheus text there, atomically, for node_exporter's textfile "
        "collector (implies -o prom; each poll rewrites it).",
    ),
    shared_option(
        "--measurement",
        default="modbus",
        show_default=True,
        help="-o influx: the measurement; -o prom: the metric names' prefix.",
    ),
    shared_option(
        "--changes",
        is_flag=True,
        help="Polling: print the first poll whole, then only the values that changed.",
    ),
]


def polling_options(function):
    """--interval and --polls, for the read commands, and what they do in --help; and the
    output options of reads (--changes, --measurement, --textfile), which go to the run's
    Settings (device_command)."""
    function.__doc__ = (function.__doc__ or "").rstrip() + POLL_HELP
    return with_options(POLLING_OPTIONS)(function)


def _run(
    connection: Connection, settings: Settings, request, to_result, interval, polls, run=None, points=()
) -> Verdict | None:
    """Once (None), or polled (how the polls ended).  ``run(execute)``: a read of several requests (a map's ``points``),
    which ``request``, the first of them, stands for."""
    if settings.name and not settings.mqtt:
        raise UsageError("--name names the device on the broker: it goes with --mqtt")
    if settings.mqtt and (settings.dry_run or (interval is None and polls is None)):
        raise UsageError("--mqtt publishes polls: give --interval or --polls (and no --dry-run)")
    metrics = None
    if settings.textfile or settings.output_format in formats(READINGS):
        settings, metrics = _metrics(connection, settings, points)
    if (interval is None and polls is None) or settings.dry_run:
        try:
            _once(connection, settings, request, to_result, run, metrics)
        except Exception as error:
            if metrics is not None:  # -o prom says the device is down
                metrics.emit_failure(error, sys.stdout)
            raise
        return None
    from mbtool.cli.poll_output import ChangesOnly, Deferred, DeferredRead, Output  # noqa: PLC0415 - polling only
    from mbtool.plant.polling import poll  # noqa: PLC0415 - polling only

    fmt = settings.output_format or default_format()
    whole = Output(fmt, csv_header=settings.csv_header, metrics=metrics)
    output: Output | ChangesOnly | PublishedPolls = ChangesOnly(whole) if settings.changes else whole
    if settings.mqtt:
        from mbtool.cli.broker import PublishedPolls  # noqa: PLC0415 - --mqtt only

        output = PublishedPolls(output, settings.mqtt, settings.name, connection.unit)
    # A read of one request is shown as its values; a map's, as its points.
    shown = (
        DeferredRead(output, to_result) if isinstance(to_result, PollsOfRead) else Deferred(output, to_result)
    )
    polled = poll(connection, request, shown, interval, polls, trace_for(settings), run)
    if settings.stats == "json":  # the summary as one JSON object, before its line
        print(to_json(polling_figures(polled)), file=sys.stderr, flush=True)
    return polling_summary(polled)


def polling_summary(polled) -> Verdict:
    """A run of polls (plant.polling.Polled) in words: the one line that ends it, with its code."""
    summary = (
        f"polls {polled.polls}, replies {polled.replies}, partial {polled.partial}, "
        f"timeouts {polled.timeouts}, errors {polled.errors}, skipped {polled.skipped}, "
        f"latency per request min/avg/max {_latency(polled.stats.rtt)}, per poll {_latency(polled.per_poll)}"
    )
    if polled.polls > 1 and polled.last_when > polled.first_when:
        summary += f", {_rate((polled.polls - 1) / (polled.last_when - polled.first_when))} polls/s"
    summary += f"; {polled.stats}"
    if polled.accepted:
        summary += f"; accepted (--lenient): {'; '.join(polled.accepted)}"
    if polled.interrupted:
        summary = "interrupted; " + summary
    return Verdict(summary, polled.exit_code)


def polling_figures(polled) -> dict:
    """A run of polls as --stats json's object."""
    return {
        "polls": polled.polls,
        "replies": polled.replies,
        "partial": polled.partial,
        "timeouts": polled.timeouts,
        "errors": polled.errors,
        "skipped": polled.skipped,
        "interrupted": polled.interrupted,
        "latency_ms": {"per_request": _ms(polled.stats.rtt), "per_poll": _ms(polled.per_poll)},
        **polled.stats.as_dict(),
    }


def _latency(durations) -> str:
    """min/avg/max in ms, of a poll's latencies or the round trips link.stats counted."""
    figures = durations.figures()
    if figures is None:
        return "-"
    return f"{figures['min'] * 1000:.1f}/{figures['avg'] * 1000:.1f}/{figures['max'] * 1000:.1f} ms"


def _ms(durations) -> dict | None:
    """min, avg and max in ms (None before the first)."""
    figures = durations.figures()
    if figures is None:
        return None
    return {name: figures[name] * 1000 for name in ("min", "avg", "max")}


def _rate(per_second: float) -> str:
    """Polls a second, from first poll to last: whole numbers when fast, two figures when slow (cron)."""
    return f"{per_second:.0f}" if per_second >= 10 else f"{per_second:.2g}"


def _once(connection: Connection, settings: Settings, request, to_result, run=None, metrics=None) -> None:
    if run is None:
        show(connection, settings, to_result(execute(connection, settings, request)), metrics)
        return

    with open_client(connection, settings, request.name) as client:
        try:
            result = to_result(run(client.execute))
        except PartialRead as partial:  # what was read is shown; the failure ends the run
            show(connection, settings, to_result(partial.readings), metrics)
            raise
        show(connection, settings, result, metrics)


# --- reads: FC 01-04 -------------------------------------------------------------------


def _metrics(connection: Connection, settings: Settings, points=()):
    """-o influx / prom and --textfile: the run's settings for them (--textfile is -o prom)
    and its Readings (the format's sink's), checked before anything is sent (with a map's ``points``)."""
    fmt = settings.output_format
    if settings.textfile:
        if fmt not in (None, "prom"):
            raise UsageError(f"--textfile writes the Prometheus text; -o {fmt} does not go with it")
        settings = replace(settings, output_format="prom")
    if settings.changes:
        raise UsageError("--changes writes a change log; -o influx and prom carry every value each poll")
    assert settings.output_format is not None  # -o influx or prom (the caller's test), or prom for --textfile
    metrics = sink(settings.output_format).Readings(settings, connection.unit)
    metrics.check(points)
    return settings, metrics


def _read_bits(
    connection: Connection,
    settings: Settings,
    kind,
    address: int,
    count: int,
    interval=None,
    polls=None,
    table=None,
) -> Verdict | None:
    """``table``: the Modicon table of a ``read REF``, whose references name the items."""
    request = kind(address, count)
    # What every poll shares, made once: a poll's result is its bits in this frame.
    addresses = list(range(address, address + count))
    refs = None if table is None else _refs(table, addresses)

    shared = Result(
        connection.unit, kind.function_code, kind.name, address, [], refs=refs, addresses=addresses
    )

    return _run(
        connection, settings, request, PollsOfRead(shared, attrgetter("bits"), list, False), interval, polls
    )


def _read_registers(
    connection: Connection,
    settings: Settings,
    kind,
    address: int,
    count: int,
    value_type: str,
    order: str,
    interval=None,
    polls=None,
    table=None,
) -> Verdict | None:
    """``table``: the Modicon table of a ``read REF``, whose references name the items."""
    if order == ORDER_ALL and TYPES[value_type].registers < 2:
        raise UsageError(
            f"--order all shows 32- and 64-bit values in each word order; {value_type} is not one: "
            "give --type float32, uint32, int32, float64, uint64 or int64"
        )
    # What every poll shares, worked out once: a poll's result is its values in this frame.
    request = kind(address, registers_needed(value_type, count))
    addresses = value_addresses(value_type, address, request.count)
    refs = None if table is None else _refs(table, addresses)
    extra = {"order": ORDER_ALL} if order == ORDER_ALL else None
    if order == ORDER_ALL:
        # The same registers read in each order, side by side: the manual's expected value
        # shows which order the device uses.
        decoders = [value_decoder(value_type, o) for o in ORDERS]

        def decode(registers):
            each = [decoded(registers) for decoded in decoders]
            return [dict(zip(ORDERS, values, strict=True)) for values in zip(*each, strict=True)]

    else:
        decode = value_decoder(value_type, order)

    # What every poll's result shares, made once: a poll's is this with its values.
    shared = Result(
        connection.unit,
        kind.function_code,
        kind.name,
        address,
        [],
        value_type,
        extra=extra,
        refs=refs,
        addresses=addresses,
    )

    polls_of = PollsOfRead(shared, attrgetter("registers"), decode, True)
    return _run(connection, settings, request, polls_of, interval, polls)


@device_command("read-coils", readings=True, polls=True)
@click.argument("address", type=ADDRESS)
@click.argument("count", type=COUNT, default=1)
@polling_options
def read_coils(connection, settings, address, count, interval, polls):
    """Read coils (FC 01). COUNT (default 1, at most 2000) bits from ADDRESS."""
    return _read_bits(connection, settings, ReadCoils, address, count, interval, polls)


@device_command("read-discrete-inputs", readings=True, polls=True)
@click.argument("address", type=ADDRESS)
@click.argument("count", type=COUNT, default=1)
@polling_options
def read_discrete_inputs(connection, settings, address, count, interval, polls):
    """Read discrete inputs (FC 02). COUNT (default 1, at most 2000) bits from ADDRESS."""
    return _read_bits(connection, settings, ReadDiscreteInputs, address, count, interval, polls)


def _refs(table, addresses: list[int]) -> list[str]:
    from mbtool.codec.tables import reference  # noqa: PLC0415 - read REF only

    return [reference(table, address) for address in addresses]


@device_command("read-holding-registers", types=VALUE_TYPES, order_all=True, readings=True, polls=True)
@click.argument("address", type=ADDRESS)
@click.argument("count", type=COUNT, default=1)
@polling_options
def read_holding_registers(connection, settings, address, count, value_type, order, interval, polls):
    """Read holding registers (FC 03). COUNT (default 1) from ADDRESS, at most 125.

    With --type, COUNT counts values of that type (float32: 2 registers each);
    for --type string it counts registers (2 characters each).
    """
    return _read_registers(
        connection, settings, ReadHoldingRegisters, address, count, value_type, order, interval, polls
    )


@device_command("read-input-registers", types=VALUE_TYPES, order_all=True, readings=True, polls=True)
@click.argument("address", type=ADDRESS)
@click.argument("count", type=COUNT, default=1)
@polling_options
def read_input_registers(connection, settings, address, count, value_type, order, interval, polls):
    """Read input registers (FC 04). COUNT (default 1) from ADDRESS, at most 125.

    With --type, COUNT counts values of that type (float32: 2 registers each);
    for --type string it counts registers (2 characters each).
    """
    return _read_registers(
        connection, settings, ReadInputRegisters, address, count, value_type, order, interval, polls
    )


# --- read: by reference, or by a register map's names ------------------------------------


@device_command("read", types=VALUE_TYPES, order_all=True, readings=True, polls=True)
@click.argument("targets", nargs=-1, metavar="REF [COUNT] | NAME...")
@map_option("points by name, scaled, with units")
@polling_options
def read(connection, settings, targets, map, value_type, order, interval, polls):
    """Read by a device manual's reference, or a register map's points by name.

    REF is a Modicon reference: 00001 coil 1, 10001 discrete input 1, 30001 input
    register 1, 40001 holding register 1; six digits reach 65536 (400001-465536);
    4x0108 is 40108. The wire address is the reference - 1 (40108 is holding register
    107). COUNT (default 1) values from there, of --type for registers.

    With -m MAP: the named points (all when none is named), in as few requests as the
    spec's limits and the map's max_gap allow; each point scaled, with its unit (plain:
    NAME VALUE UNIT lines; JSON: name, value, unit, ref and the raw registers).
    """
    given = type_options_given(map)
    if map:
        return _read_map(connection, settings, map, targets, interval, polls)
    from mbtool.codec.tables import READS  # noqa: PLC0415 - read REF only

    table, address, count = reference_target(targets, "read", given)
    kind = READS[table.name]
    if table.bits:
        return _read_bits(connection, settings, kind, address, count, interval, polls, table)
    return _read_registers(
        connection, settings, kind, address, count, value_type, order, interval, polls, table
    )


def _read_map(
    connection: Connection, settings: Settings, path: str, names, interval, polls
) -> Verdict | None:
    from mbtool.library import load_named_map  # noqa: PLC0415 - the map loader, 4-8 ms: -m only
    from mbtool.registermap.plan import MapReader  # noqa: PLC0415 - with decimal, 2 ms: -m only

    register_map = load_named_map(path)
    points = register_map.select(names)
    reader = MapReader(points, register_map.max_gap)  # one for every poll: a split read stays split
    requests = [block.request for block in reader.blocks]
    if settings.dry_run:  # no read depends on another's reply: show them all
        with open_client(connection, settings, requests[0].name) as client:
            for request in requests:
                client.show(connection.unit, request)
            client.finish(connection.unit)

    def run(execute):
        return reader.read(partial(execute, connection.unit))

    def to_result(readings):
        rows = [
            PointRow(
                r.point.name,
                r.value,
                r.point.unit,
                r.point.ref,
                r.raw,
                r.point.table.bits,
                r.point.description,
                r.point.number_of(r.value),
                r.point.no_label(r.value),
            )
            for r in readings
            if r.error is None
        ]
        failed = [
            PointFailure(r.point.name, r.point.ref, r.error.answer) for r in readings if r.error is not None
        ]
        return Points(connection.unit, register_map.source, rows, failed=failed)

    return _run(connection, settings, requests[0], to_result, interval, polls, run, points)
