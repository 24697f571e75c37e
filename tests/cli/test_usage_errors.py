"""Issue 41.6: a mistake in what the user gave (an option, an argument, a profile, an inventory)
is a UsageError, apart from the codec's RequestError (a request the spec forbids).  Both are
exit 2 with one line and nothing sent; only the class differs, so that code which catches the
codec's error (to answer an exception reply, to say which point's value broke the spec) never
swallows a user's mistake, and code that must stop on either says so.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from helpers.checks import assert_one_error_line
from helpers.run import run_cli

from mbtool.cli.commands.check import _range
from mbtool.cli.commands.diagnostics import _sub_function
from mbtool.cli.commands.dump import parse_span
from mbtool.cli.commands.exporter import parse_listen
from mbtool.cli.commands.functions import _groups
from mbtool.cli.commands.write import parse_bit
from mbtool.codec.errors import RequestError
from mbtool.errors import ExitCode, UsageError, exit_code_for
from mbtool.link.settings import TlsSettings
from mbtool.link.tls import client_context
from mbtool.link.transport import parse_target


def test_an_except_request_error_does_not_swallow_a_usage_error():
    """The codec's handlers (a server's exception reply, a reply's bad value) catch
    RequestError; a user's mistake must go past them to the command line's one line."""
    assert not issubclass(UsageError, RequestError)
    with pytest.raises(UsageError):
        try:
            raise UsageError("--range x: write it as TABLE:FIRST-LAST")
        except RequestError:  # pragma: no cover - what the codec's path does with its own
            pytest.fail("a usage error was taken for the spec's refusal")
    assert exit_code_for(UsageError("x")) == ExitCode.USAGE == exit_code_for(RequestError("x"))


@pytest.mark.parametrize(
    "mistake",
    [
        lambda: parse_span("holding:0-x"),
        lambda: _range("5:1x", "--warning", typed=True),
        lambda: _sub_function("no-such-thing"),
        lambda: parse_listen("[::1:9502"),
        lambda: parse_bit("maybe"),
        lambda: _groups(("1", "2", ",")),
        lambda: parse_target("tcp://[::1"),
        lambda: parse_target("foo://x"),
        lambda: client_context(TlsSettings(key="k.pem")),
        lambda: client_context(TlsSettings(ca="/nonexistent/ca.pem")),
    ],
    ids=[
        "dump --range",
        "check --warning",
        "diag SUBFUNCTION",
        "exporter --listen",
        "write-coil",
        "read-file",
        "-p tcp://[::1",
        "-p foo://",
        "--key alone",
        "--ca unreadable",
    ],
)
def test_a_command_line_mistake_is_a_usage_error_not_the_codecs(mistake):
    with pytest.raises(UsageError) as error:
        mistake()
    assert not isinstance(error.value, RequestError)


def test_no_command_raises_the_codecs_error_for_a_users_mistake():
    """cli/ raised RequestError 62 times for mistakes in options and files, the link's targets
    and certificates 25 times, serve's data files 25, a value written to a point of a map 8 and
    a write from the broker 3; the codec raises its own error for what the spec forbids (a
    quantity, an address, a value)."""
    mbtool = Path(__file__).resolve().parents[2] / "mbtool"
    config = (
        "link/transport.py",
        "link/tls.py",
        "device/datafile.py",
        "device/server.py",
        "registermap/point.py",  # a value written to a point, by write -m or from the broker
        "registermap/plan.py",
        "mqtt/writes.py",
    )
    paths = [*sorted((mbtool / "cli").rglob("*.py")), *(mbtool / path for path in config)]
    raised = [
        f"{path.relative_to(mbtool)}:{number}"
        for path in paths
        for number, line in enumerate(path.read_text().splitlines(), start=1)
        if "raise RequestError" in line
    ]
    assert raised == []


def test_a_config_mistake_is_still_exit_2_with_its_one_line(tmp_path):
    """The line and the code a user's script sees do not change with the class."""
    inventory = tmp_path / "plant.toml"
    inventory.write_text('[links.a]\ntarget = "sim://"\n[devices.d]\nlink = "a"\nread = ["40001 10"]\n')
    res = run_cli("poll", str(inventory), "--once", "--hex-link", "b")
    line = assert_one_error_line(res, 2)
    assert line == f"mbtool: --hex-link b: no [links.b] in {inventory} (links: a)"
    res = run_cli("dump", "-p", "sim://", "--range", "holding:9-1", str(tmp_path / "d.toml"))
    line = assert_one_error_line(res, 2)
    assert line == "mbtool: --range holding:9-1: addresses run 0..65535, FIRST no more than LAST"


def test_a_write_from_the_broker_refused_for_the_users_mistake_is_a_usage_error():
    """A /set publish for no point, a point off the allow-list, no value, a value the point
    cannot hold or a point not writable: each the user's, refused with its line, never sent."""
    from decimal import Decimal
    from types import SimpleNamespace

    from mbtool.codec.tables import HOLDING_REGISTERS
    from mbtool.mqtt.settings import MqttSettings
    from mbtool.mqtt.topics import Topics
    from mbtool.mqtt.writes import SetRequest, Writes
    from mbtool.registermap.point import Point

    points = [
        Point("setpoint", HOLDING_REGISTERS, 10, scale=Decimal("0.1"), writable=True),
        Point("level", HOLDING_REGISTERS, 11),
        Point("limit", HOLDING_REGISTERS, 12, writable=True),
    ]
    pump = SimpleNamespace(name="pump", link="bus", unit=1, tags=None, reader=SimpleNamespace(points=points))
    settings = MqttSettings(
        "localhost", 1883, False, "mbtool", "plant", writes=True, allow=("setpoint", "level")
    )
    writes = Writes(settings, Topics(settings, [pump]), [pump])
    for point, text, line in [
        ("nope", "1", "pump reads no point nope"),
        ("limit", "3", "limit is not on the allow-list (setpoint, level)"),
        ("setpoint", "", "setpoint: no value"),
        ("setpoint", "abc", "setpoint: abc is not a number"),
        ("setpoint", "22.53", "setpoint: 22.53 is not a whole number of steps of 0.1"),
        ("setpoint", "99999", "setpoint: 99999 (raw 999990) is out of range 0..65535 for uint16"),
        ("level", "3", "level (40012) is not writable: the map does not mark it rw"),
    ]:
        with pytest.raises(UsageError) as refused:
            writes.check(SetRequest("pump", point, text))
        assert not isinstance(refused.value, RequestError)
        assert str(refused.value).startswith(line)
    assert writes.check(SetRequest("pump", "setpoint", "22.5"))[0] is points[0]
