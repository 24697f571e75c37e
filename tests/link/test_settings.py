"""One table of link settings (issue 41.3): each setting once, and everything that names one
(Connection, the options, a profile's keys, an inventory's link keys) made from it."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from mbtool.cli import profiles
from mbtool.cli.options import device_command
from mbtool.cli.param_types import parse_units
from mbtool.codec.errors import RequestError
from mbtool.codec.record import fields, replace
from mbtool.errors import ExitCode, UsageError, exit_code_for
from mbtool.link.connection import Connection, changed, check, connection_of
from mbtool.link.settings import SERIAL, SETTINGS, TLS, Flag, OneOf, SerialLine, TlsSettings
from mbtool.link.transport import SerialSettings
from mbtool.plant.inventory import LINK_KEYS, load_inventory

REPO = Path(__file__).resolve().parents[2]


def test_every_connection_field_is_a_row_of_the_table_with_its_default():
    """Issue 41.3: a transport's settings are a record of their own, its fields the rows of the
    table for that transport; Connection holds the rows for every link, and the records."""
    records = {SERIAL: (SerialLine, "serial"), TLS: (TlsSettings, "tls")}
    common = {field.name for field in fields(Connection())} - {"serial", "tls"}
    assert common == {name for name, setting in SETTINGS.items() if not setting.transport}
    for transport, (kind, name) in records.items():
        rows = {row for row, setting in SETTINGS.items() if setting.transport == transport}
        assert {field.name for field in fields(kind())} == rows, transport
        assert getattr(Connection(), name) == kind()
    for name, setting in SETTINGS.items():
        where = records[setting.transport][1] if setting.transport else None
        held = getattr(getattr(Connection(), where), name) if where else getattr(Connection(), name)
        assert held == setting.default, name
    assert len(fields(Connection())) <= 11  # of 21: a serial link's and a tls:// one's all in one


def test_a_serial_ports_settings_are_the_tables_rows_with_their_defaults():
    """The serial transport's record names the table's rows and takes their defaults (it
    wrote 19200 and "E" again)."""
    line = {field.name for field in fields(SerialSettings())} - {"rs485"}  # rs485: the direction, resolved
    assert line <= {name for name, setting in SETTINGS.items() if setting.transport == SERIAL}
    for name in line:
        assert getattr(SerialSettings(), name) == SETTINGS[name].default, name


def test_a_connection_is_made_from_settings_by_their_names_each_to_its_record():
    made = connection_of(port="tls://plc7", timeout=0.5, cert="c.pem", baud=9600, echo=True)
    assert (made.port, made.timeout) == ("tls://plc7", 0.5)
    assert made.tls == TlsSettings(cert="c.pem") and made.serial == SerialLine(baud=9600, echo=True)
    assert changed(made, insecure=True, unit=3) == replace(
        made, unit=3, tls=TlsSettings("c.pem", insecure=True)
    )


def test_a_device_commands_link_options_are_the_tables_rows():
    command = device_command("probe", polls=True)(lambda connection, settings: None)
    params = {param.name: param for param in command.params}
    for name, setting in SETTINGS.items():
        param = params[name]
        assert tuple(param.opts) == setting.flags, name
        assert param.help == setting.help, name
        assert param.is_flag == isinstance(setting.kind, Flag), name
        if setting.default is not None and not isinstance(setting.kind, Flag):
            # a choice of numbers (data bits) is offered as text, and reaches the command as a number
            shown = str(setting.default) if isinstance(setting.kind, OneOf) else setting.default
            assert param.default == shown, name
            assert param.type.convert(param.default, param, None) == setting.default, name


def test_a_profile_and_an_inventory_link_take_the_tables_keys():
    assert set(profiles.KEYS) == set(SETTINGS) | {"map"}
    assert set(LINK_KEYS) == (set(SETTINGS) - {"port", "unit"}) | {"target"}
    for name, setting in SETTINGS.items():
        assert profiles.KEYS[name] == (setting.kind.toml, setting.wanted)


@pytest.mark.parametrize("module", ["mbtool.link.settings", "mbtool.plant.inventory"])
def test_the_table_and_the_inventory_loader_are_click_free(module):
    """The inventory loader no longer builds a command to borrow click's conversions."""
    code = (
        f"import sys, {module}; print(sorted(m for m in sys.modules if m.split('.')[0] in ('click', 'rich')))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, cwd=REPO)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"


@pytest.mark.parametrize(
    "name, value, read",
    [
        ("parity", "even", "E"),
        ("bytesize", "7", 7),
        ("bytesize", 8, 8),
        ("rs485_delays", 2, (0.002, 0.0)),
        ("timeout", 2, 2.0),
    ],
)
def test_a_files_value_is_read_by_its_setting(name, value, read):
    assert SETTINGS[name].read(value) == read


@pytest.mark.parametrize(
    "name, value, message",
    [
        ("baud", 0, "baud rate 0 is out of range 1..4000000"),
        ("baud", "9600", "text, where baud takes a whole number, such as 9600"),
        ("parity", "X", "'X' is not one of 'N', 'E', 'O'."),
        ("timeout", 0, "must be more than 0 seconds, not 0"),
        ("cert", 5, 'a number, where cert takes a certificate file (PEM), such as "client.pem" (beside this file unless absolute)'),
        ("echo", 1, "a number, where echo takes true or false"),
    ],
)  # fmt: skip
def test_a_files_value_its_setting_refuses_is_a_usage_error(name, value, message):
    with pytest.raises(UsageError) as error:
        SETTINGS[name].read(value)
    assert str(error.value) == message
    assert exit_code_for(error.value) == ExitCode.USAGE


def test_a_link_that_makes_no_sense_is_a_usage_error_not_the_codecs():
    """Issue 41.6: a mistake in the settings is UsageError (exit 2); RequestError is the spec's."""
    for connection in (
        Connection(),
        connection_of(port="udp://127.0.0.1:1", echo=True),
        connection_of(port="sim://", cert="c.pem"),
        Connection("tls://plc7", framer="rtu"),
    ):
        with pytest.raises(UsageError):
            check(connection)
    assert exit_code_for(UsageError("x")) == ExitCode.USAGE == exit_code_for(RequestError("x"))


def test_each_sentence_that_refuses_a_link_setting_is_written_once():
    """bridge, serve and the master checked the same things with copied messages."""
    sources = [path.read_text() for path in (REPO / "mbtool").rglob("*.py")]
    for words in (
        "RTU frames carry 8 data bits",
        "Modbus/TCP Security carries MBAP",
        "is for tls://",
        "drives the RTS line of a serial port",
    ):
        assert sum(text.count(words) for text in sources) <= 1, words


def test_a_mistake_in_a_profile_an_inventory_or_an_option_is_a_usage_error(tmp_path):
    """Issue 41.6: the config loaders and the shared options raise UsageError (exit 2), not
    the codec's RequestError, whose raises in cli/ were mostly such mistakes."""
    config = tmp_path / "config.toml"
    config.write_text('[profiles.s]\nport = "sim://"\nspeed = 9600\n')
    inventory = tmp_path / "plant.toml"
    inventory.write_text('[links.a]\ntarget = "sim://"\n[devices.d]\nlink = "b"\nread = ["40001"]\n')
    for mistake in (
        lambda: profiles.load("s", config),
        lambda: load_inventory(str(inventory)),
        lambda: parse_units("3-1"),
    ):
        with pytest.raises(UsageError):
            mistake()
