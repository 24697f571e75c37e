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
    and certificates 25 times, serve's data files 25; the codec raises its own error for what the spec forbids
    (a quantity, an address, a value)."""
    mbtool = Path(__file__).resolve().parents[2] / "mbtool"
    config = ("link/transport.py", "link/tls.py", "device/datafile.py", "device/server.py")
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
