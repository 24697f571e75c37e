"""Options shared by the commands: defined once (pip-tools' options.py), and the decorator
that gives a device command its options, its Connection and its Settings.  Their types are
cli/param_types.py's."""

from __future__ import annotations

import functools
from collections.abc import Callable

import click

from mbtool.cli.completion import complete_port, complete_profile
from mbtool.cli.param_types import COUNT, Choice, FilePath, Number, Seconds, setting_type
from mbtool.cli.parsing import DeviceCommand
from mbtool.cli.session import warn_insecure
from mbtool.cli.settings import ERRORS_AS_JSON, Settings
from mbtool.cli.sinks import READINGS, RESULTS, SINKS, formats
from mbtool.codec.errors import RequestError
from mbtool.errors import UsageError
from mbtool.link.connection import changed, connection_of
from mbtool.link.settings import SECURITY, SERIAL_LINE, SETTINGS, USE, Flag, OneOf

# --- shared options ------------------------------------------------------------------


def shared_option(*param_decls: str, **attrs) -> Callable:
    """``click.option``, but its Option is made once, when the first command takes it, and the
    same one put on every command after: what a parse finds is kept in its context, not in the
    Option.  A module's commands then make the link's options once, not once a command: a
    one-shot read imports a module of five commands and runs one."""
    made: list[click.Option] = []

    def decorate(function: Callable) -> Callable:
        if not made:
            made.append(click.Option(param_decls, **attrs))
        if isinstance(function, click.Command):
            function.params.append(made[0])
        else:  # as click.option does: the command made later takes them in this order
            function.__dict__.setdefault("__click_params__", []).append(made[0])
        return function

    return decorate


def link_option(name: str, **extra) -> Callable:
    """The option of the link setting ``name``, made from its row in ``link.settings.SETTINGS``
    (its spellings, type, default and help); ``extra``: what only the command line has."""
    setting = SETTINGS[name]
    attrs: dict = {"help": setting.help, "metavar": setting.metavar}
    if isinstance(setting.kind, Flag):
        attrs["is_flag"] = True
    else:
        attrs["type"] = setting_type(setting.kind)
        if setting.default is not None:
            # A choice of numbers (data bits) is offered as text, as --help lists it.
            attrs["default"] = str(setting.default) if isinstance(setting.kind, OneOf) else setting.default
        if setting.show_default:
            attrs["show_default"] = True
    if setting.envvar:
        attrs |= {"envvar": setting.envvar, "show_envvar": True}
    return shared_option(*setting.flags, **attrs | extra)


# The serial line's settings, shared by the master commands, serve and monitor.
SERIAL_LINE_OPTIONS = [link_option(name) for name in SERIAL_LINE]


def with_options(options: list[Callable]) -> Callable:
    """A decorator that puts these click options on a command, shown in this order."""

    def decorate(function: Callable) -> Callable:
        for option in reversed(options):
            function = option(function)
        return function

    return decorate


serial_line_options = with_options(SERIAL_LINE_OPTIONS)


# How a server treats its TCP clients and UDP sources, shared by serve and bridge.
TCP_CLIENT_OPTIONS = [
    click.option(
        "--max-clients",
        type=Number(1, 1000, "client count"),
        default=64,
        show_default=True,
        help="TCP: clients served at once. A newcomer past them takes the slot of the least "
        "recently used idle client (one that never completed a request first); with none idle it "
        "is closed at once. Both are logged.",
    ),
    click.option(
        "--idle-timeout",
        type=Seconds(),
        default=60.0,
        show_default=True,
        help="TCP: close a client that completes no request and takes no reply for SECONDS "
        "(one that never sends, sends a byte now and then, or does not read); 0 for never.",
    ),
    click.option(
        "--first-request-timeout",
        type=Seconds(),
        default=5.0,
        show_default=True,
        help="TCP: close a client that has not completed a request SECONDS after connecting; 0 for never.",
    ),
    click.option(
        "--udp-rate",
        type=Number(1, 1_000_000, "datagrams a second"),
        metavar="N",
        help="UDP: answer at most N datagrams a second from one source address (bursts of N); "
        "the rest are dropped, counted and logged once a run. Default: no limit. Whatever the "
        "rate, a datagram is one ADU: bytes after its first are dropped, so one datagram gets "
        "one reply at most.",
    ),
]


tcp_client_options = with_options(TCP_CLIENT_OPTIONS)


def output_chosen(ctx: click.Context, param: click.Parameter, fmt: str | None) -> str | None:
    """-o's callback: noted in the run's context as soon as it is parsed, so that even a
    failure after it gets its JSON object (cli.program.main)."""
    if fmt is not None and SINKS[fmt].errors:
        ctx.meta[ERRORS_AS_JSON] = True
    return fmt


NO_HEADER_OPTION = shared_option(
    "--no-header",
    is_flag=True,
    help="CSV without its header row (it is left out anyway when appending to a file that has content).",
)

# How the master uses its link, shared by the device commands and bridge.
LINK_OPTIONS = [link_option(name) for name in USE]

# Modbus/TCP Security's certificates (tls:// targets), shared by the device commands and bridge;
# each is a profile and inventory link key too.
TLS_OPTIONS = [link_option(name) for name in SECURITY]

WRITE_ROLES_OPTION = click.option(
    "--write-roles",
    metavar="ROLE,...",
    help="tls://: the roles (from the clients' certificates, extension 1.3.6.1.4.1.50316.802.1) "
    "that may write; any other may only read (FC 01-04, 07, 0B, 0C, 11, 14, 18, 43/14, and FC 08's "
    "echo and counters): anything else it sends gets exception 01. Default: a data file's "
    "write_roles, else every client may write.",
)
# serve's: its own certificate, and the CA its clients' certificates must be signed by.
SERVE_TLS_OPTIONS = [
    click.option(
        "--cert",
        metavar="FILE",
        type=FilePath(dir_okay=False),
        help="tls://: the server's certificate (PEM, its chain after it).",
    ),
    click.option(
        "--key",
        metavar="FILE",
        type=FilePath(dir_okay=False),
        help="tls://: its private key (PEM) where --cert's file has none; an encrypted one's "
        "password is asked on the terminal or read from MBTOOL_KEY_PASSWORD.",
    ),
    click.option(
        "--ca",
        metavar="FILE",
        type=FilePath(dir_okay=False),
        help="tls://: the CA certificates (PEM) the clients' certificates must be signed by: "
        "Modbus/TCP Security requires one from every client.",
    ),
    WRITE_ROLES_OPTION,
]
serve_tls_options = with_options(SERVE_TLS_OPTIONS)

PORT_OPTION = link_option("port", shell_complete=complete_port)
UNIT_OPTION = link_option("unit")
FRAMER_OPTION = link_option("framer")
RECONNECT_EACH_OPTION = link_option("reconnect_each")
HEX_OPTION = shared_option(
    "--hex",
    "hex_trace",
    is_flag=True,
    help="Print every frame sent and received (stderr), checksum checked.",
)
OUTPUT_FORMAT_OPTION = shared_option(
    "-o",
    "--format",
    "output_format",
    type=Choice(formats(RESULTS, READINGS)),
    callback=output_chosen,
    help="Output format: table on a terminal, plain in a pipe. With json a failure is an "
    'object too: {"error": ..., "exit_code": N}. influx (InfluxDB line protocol) and prom '
    "(Prometheus text) for the read commands.",
)
DRY_RUN_OPTION = shared_option(
    "--dry-run",
    is_flag=True,
    help="Print the frame that would be sent, decoded, and send nothing (the port is not opened).",
)


# The parameters connection_options may give a command, as click names them: those that
# make its Connection (every link setting), and those that make its Settings.
CONNECTION_KEYS = tuple(SETTINGS)
SETTINGS_KEYS = (
    "hex_trace",
    "output_format",
    "no_header",
    "dry_run",
    "measurement",
    "textfile",
    "changes",
    "stats",
    "mqtt",
    "name",
)


def connection_options(unit: bool = True, output: bool = True, polls: bool = False) -> list[Callable]:
    """The options of a command that talks to a device, only those it uses: ``unit`` -u
    (raw takes the unit from its bytes), ``output`` -o and --no-header (dump writes a data
    file, check a plugin's line), ``polls`` --reconnect-each (only a poll has a next link)."""
    return [
        PORT_OPTION,
        *([UNIT_OPTION] if unit else []),
        FRAMER_OPTION,
        *SERIAL_LINE_OPTIONS,
        *LINK_OPTIONS,
        *TLS_OPTIONS,
        *([RECONNECT_EACH_OPTION] if polls else []),
        HEX_OPTION,
        *([OUTPUT_FORMAT_OPTION, NO_HEADER_OPTION] if output else []),
        DRY_RUN_OPTION,
    ]


VALUE_TYPES = ("uint16", "int16", "uint32", "int32", "float32", "uint64", "int64", "float64", "hex", "string")
ONE_REGISTER_TYPES = ("uint16", "int16", "hex")


ORDER_ALL = "all"  # --order all: a read shows its values in each of the four orders


@functools.cache  # the same --type and --order for every command that offers these choices
def type_options(choices: tuple[str, ...], order_all: bool = False) -> tuple[Callable, ...]:
    orders = ["ABCD", "CDAB", "BADC", "DCBA"] + ([ORDER_ALL] if order_all else [])
    order_help = (
        "Byte order of multi-register values: ABCD big-endian, CDAB word-swapped, "
        "BADC byte-swapped, DCBA little-endian."
    )
    if order_all:
        order_help += " all: each 32- or 64-bit value in all four, side by side, to find the device's."
    return (
        shared_option(
            "--type",
            "value_type",
            type=Choice(choices),
            default="uint16",
            show_default=True,
            help="How values map to registers.",
        ),
        shared_option("--order", type=Choice(orders), default="ABCD", show_default=True, help=order_help),
    )


# nan and inf are refused unless asked for: a typo (or 1e400, out of range) must not send one.
NONFINITE_OPTION = click.option(
    "--allow-nonfinite",
    is_flag=True,
    help="Let a float value be nan, inf or -inf (refused otherwise).",
)


def map_option(what: str) -> Callable:
    """-m/--map MAP for read and write; ``what``: what the command does with the points."""
    return click.option(
        "-m",
        "--map",
        "map",
        metavar="MAP",
        type=FilePath(dir_okay=False),
        help=f"A register map (TOML, or CSV with a header row), or a map's name (mbtool maps list): "
        f"{what}. Also a profile's map key.",
    )


def type_options_given(map_path: str | None = None) -> list[str]:
    """--type and --order, those given rather than left at their default; with a map,
    none may be: the map gives each point's own (UsageError, exit 2)."""
    ctx = click.get_current_context()
    given = [
        option
        for param, option in (("value_type", "--type"), ("order", "--order"))
        if ctx.get_parameter_source(param) is not click.core.ParameterSource.DEFAULT
    ]
    if map_path and given:
        raise UsageError(f"{given[0]} does not apply with -m: the map gives each point's type and order")
    return given


def reference_target(targets: tuple[str, ...], command: str, types_given: list[str]):
    """REF [COUNT] as read and check take them: the table, the wire address and the count.

    A name where a reference goes is told about -m; --type or --order on coils and
    discrete inputs is refused (they hold bits)."""
    from mbtool.codec.tables import parse_reference  # noqa: PLC0415 - REF only; all commands load this

    if not targets:
        raise click.UsageError("give a reference such as 40001 (and a count), or -m MAP and point names")
    if len(targets) > 2:
        raise click.UsageError(
            f"{command} takes REF [COUNT], not {len(targets)} arguments (points by name need -m MAP)"
        )
    text = targets[0]
    try:
        table, address = parse_reference(text)
    except RequestError as error:
        if text[:1].isdigit():  # a reference mistyped (4o001); a name starts with a letter (voltage_l1)
            raise
        raise UsageError(f"{error}; to {command} a point by name, give its map: -m MAP") from None
    count = COUNT.convert(targets[1], None, click.get_current_context()) if len(targets) == 2 else 1
    if table.bits and types_given:
        raise UsageError(f"{types_given[0]} is for registers; {text} is {table.item} {address + 1}, a bit")
    return table, address, count


def _remember_profile(ctx: click.Context, param: click.Parameter, value: str | None) -> None:
    # Kept aside, not passed on: the profile fills in options only after all are parsed.
    ctx.meta["mbtool.profile"] = value


PROFILE_OPTION = shared_option(  # the profile is read by device_command, or by a command itself
    "-P",
    "--profile",
    metavar="NAME",
    expose_value=False,
    callback=_remember_profile,
    shell_complete=complete_profile,
    help="Connection settings from [profiles.NAME] in $MBTOOL_CONFIG or ~/.config/mbtool/config.toml; "
    "options and MBTOOL_PORT/MBTOOL_UNIT override them.",
)


def device_command(
    name: str,
    *,
    types: tuple[str, ...] = (),
    order_all: bool = False,
    readings: bool = False,
    polls: bool = False,
    unit: bool = True,
    output: bool = True,
    **attrs,
) -> Callable:
    """A command that talks to a device: the shared options it uses, then a Connection and
    the run's Settings as first arguments.

    ``types``: the --type choices the command offers (none: no --type/--order);
    ``order_all``: --order also takes all (reads); ``readings``: it prints values read,
    which -o influx and -o prom can carry; ``polls``, ``unit``, ``output``: see
    connection_options; ``attrs``: click.command's.
    """

    def decorate(function: Callable) -> Callable:
        @functools.wraps(function)
        def run(**kwargs):
            # The command's own arguments stay in kwargs; the shared options make the
            # Connection and the Settings.
            shared = {key: kwargs.pop(key) for key in CONNECTION_KEYS if key in kwargs}
            connection = connection_of(**shared)
            shown = {key: kwargs.pop(key) for key in SETTINGS_KEYS if key in kwargs}
            output_format = shown.get("output_format")
            profile = click.get_current_context().meta.get("mbtool.profile")
            if output_format in formats(READINGS) and not readings:
                raise UsageError(
                    f"-o {output_format} carries values read: it is for read and read-coils ... read-input-registers"
                )
            settings = Settings(
                output_format=output_format,
                csv_header=not shown.get("no_header", False),
                hex=shown["hex_trace"],
                dry_run=shown["dry_run"],
                measurement=shown.get("measurement", "modbus"),
                textfile=shown.get("textfile") or "",
                # The profile names the device in what -o influx and -o prom write; --textfile
                # alone, which implies -o prom, has never carried it.
                device=(profile or "") if output_format in formats(READINGS) else "",
                changes=shown.get("changes", False),
                stats=shown.get("stats", "line"),
                mqtt=shown.get("mqtt") or "",
                name=shown.get("name") or "",
            )
            if profile:
                from mbtool.cli.profiles import defaults  # noqa: PLC0415 - -P only; all commands load this

                changes = defaults(profile)
                # A profile's key for the command's own option (map) goes to the command.
                kwargs |= {key: changes.pop(key) for key in list(changes) if key in kwargs}
                connection = changed(connection, **changes)
            if not settings.dry_run:
                warn_insecure(connection)
            return function(connection, settings, **kwargs)

        run = PROFILE_OPTION(run)
        typed = list(type_options(types, order_all)) if types else []
        run = with_options(connection_options(unit, output, polls) + typed)(run)
        # Negative register values (write-register 100 -5) must not be taken for options.
        context = {
            "ignore_unknown_options": True,
            "help_option_names": ["-h", "--help"],
            **attrs.pop("context_settings", {}),
        }
        command_class = attrs.pop("cls", DeviceCommand)  # check's: every outcome a plugin state
        return click.command(name, cls=command_class, context_settings=context, **attrs)(run)

    return decorate
