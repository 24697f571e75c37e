"""The shared options in-process (mbtool.cli.options, param_types, parsing, profiles): what
``device_command`` makes of a command line (the Connection and the Settings it hands the
command), the option types' conversions and refusals, the parsing of negative numbers and
mistyped options, and a profile's place in the precedence option > environment > profile >
default.

A toy command made with ``device_command`` records what it was given; nothing is opened.
"""

from __future__ import annotations

import click
import pytest

from mbtool.cli.options import device_command
from mbtool.cli.param_types import (
    ADDRESS,
    PARITY,
    Choice,
    Number,
    PositiveFloat,
    Rs485Delays,
    Seconds,
    parse_int,
    parse_units,
    units_text,
)
from mbtool.cli.parsing import did_you_mean
from mbtool.cli.settings import ERRORS_AS_JSON, Settings
from mbtool.errors import UsageError
from mbtool.link.connection import Connection, connection_of


@device_command("probe", types=("uint16", "float32"), readings=True, polls=True)
@click.argument("values", nargs=-1)
@click.option("-m", "--map", "map", default=None)
def probe(connection, settings, values, map, value_type, order):
    """What a device command gets: returned for the test to look at."""
    return connection, settings, {"values": values, "map": map, "value_type": value_type, "order": order}


@device_command("quiet")
def quiet(connection, settings):
    """A command that prints no values read: -o influx and -o prom are not for it."""
    return connection, settings


@pytest.fixture(autouse=True)
def no_environment(monkeypatch, tmp_path):
    """No MBTOOL_ variable and no config file but the test's own."""
    for name in ("MBTOOL_PORT", "MBTOOL_UNIT", "MBTOOL_CONFIG"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path / "no-config"))


def invoke(command: click.Command, *args: str):
    """The command run on ``args`` as click runs it, its return value and its context's meta."""
    with command.make_context(command.name, list(args)) as ctx:
        return command.invoke(ctx), ctx.meta


def given(*args: str) -> tuple[Connection, Settings, dict]:
    return invoke(probe, *args)[0]


def refused(*args: str, command: click.Command = probe) -> str:
    """The message of the error the command line ends in (click's usage error or mbtool's)."""
    with pytest.raises((click.ClickException, UsageError)) as error:
        invoke(command, *args)
    failure = error.value
    return failure.format_message() if isinstance(failure, click.ClickException) else str(failure)


# --- device_command: the Connection and the Settings ---------------------------------------


def test_no_options_are_the_defaults_of_connection_and_settings():
    connection, settings, own = given()
    assert connection == Connection()
    assert settings == Settings()
    assert own == {"values": (), "map": None, "value_type": "uint16", "order": "ABCD"}


def test_every_link_option_reaches_the_connection_converted():
    connection, _, _ = given(
        "-p", "/dev/ttyUSB0", "-u", "0x11", "--framer", "ASCII", "-b", "9600", "--parity", "even",
        "--bytesize", "7", "--stopbits", "2", "-t", "0.5", "--retries", "2", "--echo", "--pause", "0",
        "--connect-delay", "0.25", "--lenient", "--rs485-delays", "1,2.5", "--reconnect-each",
    )  # fmt: skip
    assert connection == connection_of(
        port="/dev/ttyUSB0",
        unit=17,
        framer="ascii",
        baud=9600,
        parity="E",
        bytesize=7,
        stopbits=2,
        timeout=0.5,
        retries=2,
        echo=True,
        pause=0.0,
        connect_delay=0.25,
        lenient=True,
        rs485_delays=(0.001, 0.0025),
        reconnect_each=True,
    )


def test_the_tls_options_reach_the_connection_and_insecure_is_warned_of(capsys):
    connection, _, _ = given(
        "-p", "tls://plc7:802", "--cert", "c.pem", "--key", "k.pem", "--ca", "ca.pem",
        "--server-name", "plc7.plant.example",
    )  # fmt: skip
    assert connection == connection_of(
        port="tls://plc7:802", cert="c.pem", key="k.pem", ca="ca.pem", server_name="plc7.plant.example"
    )
    connection, _, _ = given("-p", "tls://plc7:802", "--cert", "c.pem", "--insecure")
    assert connection.tls.insecure is True
    assert capsys.readouterr().err.startswith(
        "mbtool: warning: --insecure: the certificate of tls://plc7:802 "
    )
    given("-p", "tls://plc7:802", "--insecure", "--dry-run")  # a dry run opens nothing to warn of
    assert capsys.readouterr().err == ""
    # --insecure with --ca is a contradiction, said alone, before any warning.
    assert refused("-p", "tls://plc7:802", "--ca", "ca.pem", "--insecure").startswith("--insecure checks no")
    assert capsys.readouterr().err == ""


def test_the_output_options_make_the_settings_and_the_commands_own_stay_its_own():
    (_, settings, own), meta = invoke(
        probe,
        "-o",
        "json",
        "--no-header",
        "--hex",
        "--dry-run",
        "--type",
        "FLOAT32",
        "--order",
        "cdab",
        "1",
        "-5",
    )
    assert settings == Settings(output_format="json", csv_header=False, hex=True, dry_run=True)
    assert own == {"values": ("1", "-5"), "map": None, "value_type": "float32", "order": "CDAB"}
    assert meta[ERRORS_AS_JSON] is True  # a failure after -o json is a JSON object too


def test_a_metrics_format_is_for_commands_that_read_values():
    _, settings, _ = given("-o", "prom")
    assert settings.output_format == "prom"
    assert "-o influx carries values read" in refused("-o", "influx", command=quiet)


def test_the_environment_gives_port_and_unit_where_the_options_do_not(monkeypatch):
    monkeypatch.setenv("MBTOOL_PORT", "sim://")
    monkeypatch.setenv("MBTOOL_UNIT", "7")
    connection, _, _ = given()
    assert (connection.port, connection.unit) == ("sim://", 7)
    connection, _, _ = given("-p", "tcp://h", "-u", "8")
    assert (connection.port, connection.unit) == ("tcp://h", 8)


# --- profiles: option > environment > profile > default -------------------------------------

PROFILES = """
[profiles.boiler]
port = "/dev/ttyUSB0"
unit = 17
baud = 9600
parity = "none"
timeout = 0.5
bytesize = 7
echo = true
rs485_delays = "1,2"
map = "maps/boiler.toml"
ca = "/etc/plant/ca.pem"
"""


@pytest.fixture
def config(tmp_path, monkeypatch):
    path = tmp_path / "config.toml"
    path.write_text(PROFILES)
    monkeypatch.setenv("MBTOOL_CONFIG", str(path))
    return path


def test_a_profile_fills_in_what_the_options_left_at_their_default(config):
    connection, settings, own = given("-P", "boiler")
    assert connection == connection_of(
        port="/dev/ttyUSB0",
        unit=17,
        baud=9600,
        parity="N",
        timeout=0.5,
        bytesize=7,
        echo=True,
        rs485_delays=(0.001, 0.002),
        ca="/etc/plant/ca.pem",
    )
    assert own["map"] == str(config.parent / "maps" / "boiler.toml")  # beside the config file
    assert settings.device == ""  # the profile names the device only in metrics


def test_options_and_the_environment_win_over_the_profile(config, monkeypatch):
    monkeypatch.setenv("MBTOOL_UNIT", "3")
    connection, _, own = given("-P", "boiler", "-b", "19200", "-m", "other.toml")
    assert (connection.unit, connection.serial.baud, connection.port) == (3, 19200, "/dev/ttyUSB0")
    assert own["map"] == "other.toml"
    connection, _, _ = given("-P", "boiler", "-u", "4")  # the option over the environment
    assert connection.unit == 4


def test_an_option_given_at_its_default_value_still_wins_over_the_profile(config):
    connection, _, _ = given("-P", "boiler", "--parity", "E", "-t", "1")
    assert (connection.serial.parity, connection.timeout) == ("E", 1.0)


def test_a_profile_names_the_device_in_what_the_metrics_formats_write(config):
    _, settings, _ = given("-P", "boiler", "-o", "influx")
    assert settings.device == "boiler"


@pytest.mark.parametrize(
    "text, words",
    [
        ("[profiles.boiler]\nspeed = 1\n", "profiles.boiler.speed: unknown key"),
        (
            "[profiles.boiler]\nunit = true\n",
            "profiles.boiler.unit: true/false, where unit takes a whole number",
        ),
        ('[profiles.boiler]\nunit = "x"\n', "profiles.boiler.unit: text, where unit takes a whole number"),
        ("[profiles.boiler]\nunit = 300\n", "profiles.boiler.unit: unit 300 is out of range 0..255"),
        ('[profiles.boiler]\nparity = "X"\n', "profiles.boiler.parity:"),
        (
            "[profiles.boiler]\nbaud = 9600.5\n",
            "profiles.boiler.baud: a number, where baud takes a whole number",
        ),
        ("[profiles.other]\nunit = 1\n", "no profile boiler (profiles: other)"),
        ("[profiles]\nboiler = 1\n", "[profiles.boiler] must be a table"),
        ("[profiles.boiler\n", "not valid TOML"),
    ],
)
def test_a_bad_profile_is_one_error_naming_the_file(tmp_path, monkeypatch, text, words):
    path = tmp_path / "config.toml"
    path.write_text(text)
    monkeypatch.setenv("MBTOOL_CONFIG", str(path))
    message = refused("-P", "boiler")
    assert message.startswith(str(path)) and words in message


def test_a_profile_file_that_is_not_there_is_named(tmp_path, monkeypatch):
    monkeypatch.setenv("MBTOOL_CONFIG", str(tmp_path / "none.toml"))
    assert refused("-P", "boiler").startswith(f"cannot read profile file {tmp_path / 'none.toml'}: ")


# --- the option types --------------------------------------------------------------------


@pytest.mark.parametrize(
    "text, number",
    [
        ("10", 10),
        ("007", 7),
        ("0x1F", 31),
        ("0X1f", 31),
        ("0o17", 15),
        ("0b101", 5),
        ("-3", -3),
        (" 4 ", 4),
        ("+5", 5),
    ],
)
def test_numbers_are_decimal_or_prefixed(text, number):
    assert parse_int(text) == number


@pytest.mark.parametrize("text, shown", [("abc", "abc"), ("", "(empty)"), ("0x", "0x"), ("1.5", "1.5")])
def test_what_is_no_number_is_named(text, shown):
    with pytest.raises(UsageError) as error:
        parse_int(text, "unit")
    assert str(error.value) == f"unit {shown} is not a number (decimal or 0x hex)"


@pytest.mark.parametrize(
    "text, units",
    [("1", {1}), ("1,17", {1, 17}), ("1-3,17", {1, 2, 3, 17}), ("0x10-0x11", {16, 17}), ("255", {255})],
)
def test_unit_lists(text, units):
    assert parse_units(text) == units


@pytest.mark.parametrize(
    "text, words",
    [
        ("0", "unit 0 is out of range 1..255 (unit 0 is broadcast"),
        ("256", "unit 256 is out of range 1..255"),
        ("3-1", "unit range 3-1 runs backwards"),
        ("1,,2", "empty unit id in 1,,2"),
        ("x", "unit x is not a number"),
    ],
)
def test_bad_unit_lists(text, words):
    with pytest.raises(UsageError) as error:
        parse_units(text)
    assert words in str(error.value)


def test_broadcast_may_be_listed_where_a_gateway_forwards_it():
    assert parse_units("0-2", broadcast=True) == {0, 1, 2}
    with pytest.raises(UsageError, match=r"out of range 0\.\.255$"):
        parse_units("256", broadcast=True)


def test_unit_lists_are_shown_as_runs():
    assert units_text(frozenset({1, 2, 3, 17, 19, 20})) == "1-3,17,19-20"


def convert(kind: click.ParamType, value):
    return kind.convert(value, None, None)


def failure(kind: click.ParamType, value) -> str:
    with pytest.raises(click.BadParameter) as error:
        convert(kind, value)
    return error.value.message


def test_number_in_range():
    assert convert(ADDRESS, "0xFFFF") == 65535 and convert(ADDRESS, 7) == 7
    assert failure(ADDRESS, "65536") == "address 65536 is out of range 0..65535"
    assert (
        failure(Number(1, 4_000_000, "baud rate"), "fast")
        == "baud rate fast is not a number (decimal or 0x hex)"
    )


@pytest.mark.parametrize("value", ["0.5", "2", "1e-3"])
def test_seconds_more_than_zero(value):
    assert convert(PositiveFloat(), value) == float(value)


@pytest.mark.parametrize(
    "value, message",
    [
        ("0", "must be more than 0 seconds, not 0"),
        ("-1", "must be more than 0 seconds, not -1"),
        ("nan", "must be more than 0 seconds, not nan"),
        ("inf", "must be more than 0 seconds, not inf"),
        ("soon", "soon is not a number of seconds"),
    ],
)
def test_seconds_refused(value, message):
    assert failure(PositiveFloat(), value) == message


def test_seconds_that_may_be_zero():
    assert convert(PositiveFloat(zero_ok=True), "0") == 0.0
    assert failure(PositiveFloat(zero_ok=True), "-0.1") == "must be 0 or more seconds, not -0.1"
    assert convert(Seconds(), "0") == 0.0 and convert(Seconds(), "60") == 60.0
    assert failure(Seconds(), "-1") == "-1 is not a number of seconds (0 for never)"
    assert failure(Seconds(), "nan") == "nan is not a number of seconds (0 for never)"


@pytest.mark.parametrize(
    "value, delays", [("1", (0.001, 0.0)), ("1,2.5", (0.001, 0.0025)), ("0,1000", (0.0, 1.0))]
)
def test_rs485_delays_in_milliseconds_kept_in_seconds(value, delays):
    assert convert(Rs485Delays(), value) == delays


@pytest.mark.parametrize(
    "value, message",
    [
        ("1,2,3", "1,2,3: give BEFORE[,AFTER], each 0..1000 ms"),
        ("1001", "1001: give BEFORE[,AFTER], each 0..1000 ms"),
        ("-1", "-1: give BEFORE[,AFTER], each 0..1000 ms"),
        ("a,b", "a,b is not BEFORE[,AFTER] in milliseconds"),
    ],
)
def test_rs485_delays_refused(value, message):
    assert failure(Rs485Delays(), value) == message


def test_choices_in_any_case_come_out_as_listed_and_aliases_as_their_choice():
    order = Choice(["ABCD", "CDAB"])
    assert convert(order, "cdab") == "CDAB"
    assert [convert(PARITY, word) for word in ("n", "E", "odd", "NONE", "Even")] == ["N", "E", "O", "N", "E"]
    assert "'X' is not one of 'N', 'E', 'O'" in failure(PARITY, "X")
    assert [item.value for item in PARITY.shell_complete(None, None, "")] == ["N", "E", "O"]
    assert [item.value for item in order.shell_complete(None, None, "c")] == ["CDAB"]


# --- parsing: negative numbers, mistyped options ---------------------------------------------


def test_negative_numbers_are_arguments_not_options():
    _, _, own = given("100", "-5", "-0x10", "-1.5e3")
    assert own["values"] == ("100", "-5", "-0x10", "-1.5e3")


def test_short_options_and_values_joined_to_them():
    connection, _, _ = given("-u17", "-t0.5", "--baud=9600")
    assert (connection.unit, connection.timeout, connection.serial.baud) == (17, 0.5, 9600)


def test_a_mistyped_option_is_refused_with_the_close_ones():
    assert refused("--boud", "9600") == "no such option --boud; did you mean --baud or --order?"
    assert refused("--timout=1") == "no such option --timout; did you mean --timeout?"
    assert refused("--zzz") == "no such option --zzz"


def test_after_a_double_dash_everything_is_an_argument():
    _, _, own = given("--", "--baud", "-x")
    assert own["values"] == ("--baud", "-x")


@pytest.mark.parametrize(
    "close, said",
    [
        ([], ""),
        (["read"], "; did you mean read?"),
        (["a", "b"], "; did you mean a or b?"),
        (["a", "b", "c"], "; did you mean a, b or c?"),
    ],
)
def test_did_you_mean(close, said):
    assert did_you_mean(close) == said
