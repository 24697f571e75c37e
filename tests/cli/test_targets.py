"""What -p names, checked before anything is opened (issues 12.10, 12.12, 13.5).

A malformed or unknown target is exit 2 with one line; a host typed without tcp://
gets the URL it probably meant; a serial device that is not there lists those that
are; a serial port another program holds is exit 6 "port busy".
"""

from __future__ import annotations

import os
import re
import threading
import tty

import pytest
from helpers.checks import assert_one_error_line
from helpers.ptys import PTY_SERIAL_OPTS
from helpers.run import run_cli

from mbtool.cli.program import register_schemes
from mbtool.errors import UsageError
from mbtool.link.transport import parse_target

register_schemes()  # sim://, as the command line's main() registers it

pytestmark = pytest.mark.timeout(60)


@pytest.mark.parametrize(
    "target, words",
    [
        ("tcp://[::1", "an IPv6 address goes in brackets"),
        ("tcp://::1", "an IPv6 address goes in brackets"),
        ("socket://127.0.0.1", r"no port in socket://127.0.0.1 \(expected socket://HOST:PORT\)"),
        ("rfc2217://", "no host in rfc2217://"),
        ("tcp://127.0.0.1:0", "bad port 0 in tcp://127.0.0.1:0: a TCP port is 1..65535"),
        ("tcp://127.0.0.1:65536", "bad port 65536"),
        ("tcp://127.0.0.1:http", "bad port http"),
        ("tcp://:502", "no host in tcp://:502"),
        ("rtu+udp://10.0.0.7", r"no port in rtu\+udp://10.0.0.7 \(expected rtu\+udp://HOST:PORT\)"),
        ("udp://127.0.0.1:0", "bad port 0 in udp://127.0.0.1:0: a UDP port is 1..65535"),
        ("tls://[::1", "an IPv6 address goes in brackets"),
        ("foo://bar", r"unknown scheme foo:// in foo://bar: use tcp://HOST\[:PORT\]"),
        ("", "no port given"),
    ],
)
def test_a_malformed_target_is_exit_2_before_anything_is_opened(target, words):
    res = run_cli("read-holding-registers", "0", "-p", target, "-t", "0.5")
    line = assert_one_error_line(res, 2)
    assert re.search(words, line), line


@pytest.mark.parametrize(
    "target, meant",
    [
        ("127.0.0.1:15020", "tcp://127.0.0.1:15020"),
        ("plc.local", "tcp://plc.local"),
        ("localhost:502", "tcp://localhost:502"),
    ],
)
def test_a_bare_host_gets_the_url_it_probably_meant(target, meant):
    res = run_cli("read-holding-registers", "0", "-p", target)
    line = assert_one_error_line(res, 2)
    assert line == f"mbtool: {target} is not a serial device; did you mean {meant}?"


def test_a_file_named_like_a_host_is_still_a_device(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "plc.local").touch()
    assert parse_target("plc.local").path == "plc.local"


@pytest.mark.parametrize(
    "target, scheme, host, port",
    [
        ("tcp://10.0.0.5", "tcp", "10.0.0.5", 502),
        ("TCP://[::1]:5020/", "tcp", "::1", 5020),
        ("tls://plc7.plant.example", "tls", "plc7.plant.example", 802),
        ("tls://10.0.0.5:8802", "tls", "10.0.0.5", 8802),
        ("udp://10.0.0.5", "udp", "10.0.0.5", 502),
        ("UDP://[::1]:5020", "udp", "::1", 5020),
        ("rtu+udp://10.0.0.7:4001", "rtu+udp", "10.0.0.7", 4001),
        ("socket://gw:4001?logging=debug", "serial", "gw", 4001),
        ("sim://", "sim", "", 0),
        ("/dev/ttyUSB0", "serial", "", 0),
        ("loop://", "serial", "", 0),
    ],
)
def test_good_targets(target, scheme, host, port):
    parsed = parse_target(target)
    assert (parsed.scheme, parsed.host, parsed.port) == (scheme, host, port)
    if scheme == "serial":
        assert parsed.path == target  # handed to pyserial as typed, options and all


@pytest.mark.parametrize(
    "target, words",
    [
        ("loop://?x=1", "loop://?x=1: loop:// takes no option 'x' (its options: logging)"),
        ("loop://?logging=loud", "loop://?logging=loud: logging is one of debug, info, warning, error"),
        ("hwgrep://((", "hwgrep://((: '((' is no regular expression"),
        ("hwgrep://USB&n=x", "hwgrep://USB&n=x: n=x: expected a whole number, 2 or more"),
        ("socket://127.0.0.1:1?logging=debug&x", "takes no option 'x'"),
        ("rfc2217://127.0.0.1:1?timeout=inf", "timeout=inf: expected a number of seconds"),
        ("spy://loop://?file=", "file needs a value"),
    ],
)
def test_a_pyserial_url_with_a_bad_option_is_exit_2_in_read_and_poll(tmp_path, target, words):
    """Issue 40.16: pyserial met these with KeyError or re.error, an internal error (exit 1)."""
    res = run_cli("read-holding-registers", "0", "-p", target, "-t", "0.2")
    assert words in assert_one_error_line(res, 2)
    plant = tmp_path / "plant.toml"
    plant.write_text(f'[links.a]\ntarget = "{target}"\n[devices.d]\nlink = "a"\nread = ["40001 1"]\n')
    res = run_cli("poll", plant, "--once", "-o", "plain")
    assert words in assert_one_error_line(res, 2)


@pytest.mark.parametrize(
    "target, one",
    [
        ("tcp://127.0.0.01", "tcp://127.0.0.1:502"),
        ("TCP://127.1:502/", "tcp://127.0.0.1:502"),
        ("tcp://0x7f.0.0.1", "tcp://127.0.0.1:502"),
        ("tcp://2130706433", "tcp://127.0.0.1:502"),
        ("tcp://127.0.0.010", "tcp://127.0.0.8:502"),  # octal, as the resolver reads it
        ("udp://[0:0::1]:5020", "udp://[::1]:5020"),
        ("tls://[FE80::1%eth0]", "tls://[fe80::1%eth0]:802"),
        ("tcp://PLC7.Plant.Example.", "tcp://plc7.plant.example:502"),
        ("socket://127.000.0.1:4001?logging=debug", "socket://127.0.0.1:4001"),
        ("/dev/ttyUSB0", "/dev/ttyUSB0"),
    ],
)
def test_a_targets_normalised_form_is_one_spelling_of_its_link(target, one):
    """Issue 40.1: what an exporter's --allow-target patterns match, and its locks are keyed by."""
    assert str(parse_target(target).normalised()) == one


def test_a_server_may_listen_on_port_0():
    for scheme in ("tcp", "tls", "udp", "rtu+udp"):
        assert parse_target(f"{scheme}://127.0.0.1:0", listening=True).port == 0
        with pytest.raises(UsageError):
            parse_target(f"{scheme}://127.0.0.1:0")


@pytest.mark.parametrize(
    "target, shown, framing",
    [
        ("tcp://[::1]:5020", "tcp://[::1]:5020", "tcp"),
        ("tls://10.0.0.5", "tls://10.0.0.5:802", "tcp"),
        ("udp://10.0.0.5", "udp://10.0.0.5:502", "tcp"),
        ("rtu+udp://10.0.0.7:4001", "rtu+udp://10.0.0.7:4001", "rtu"),
        ("/dev/ttyUSB0", "/dev/ttyUSB0", "rtu"),
    ],
)
def test_a_target_shows_its_port_and_names_its_framing(target, shown, framing):
    from mbtool.link.transport import default_framer

    assert str(parse_target(target)) == shown
    assert default_framer(target) == framing


def test_a_missing_serial_device_lists_the_ports_that_exist():
    res = run_cli("read-holding-registers", "0", "-p", "/dev/ttyNOPE0")
    line = assert_one_error_line(res, 6)
    assert line.startswith("mbtool: cannot open /dev/ttyNOPE0: no such device (")
    assert "serial ports here:" in line or "no serial ports found here" in line


def test_a_serial_port_in_use_is_port_busy_and_nothing_is_sent():
    """Two programs on one port split the replies between them: the second is refused."""
    master, slave = os.openpty()
    tty.setraw(master)
    path = os.ttyname(slave)
    import serial

    holder = serial.Serial(path, exclusive=True)  # another program, holding the port
    received = bytearray()
    stop = threading.Event()

    def drain() -> None:
        import select

        while not stop.is_set():
            if select.select([master], [], [], 0.05)[0]:
                received.extend(os.read(master, 4096))

    reader = threading.Thread(target=drain, daemon=True)
    reader.start()
    try:
        res = run_cli("read-holding-registers", "0", "-p", path, *PTY_SERIAL_OPTS, "-t", "0.3")
        line = assert_one_error_line(res, 6)
        assert line == f"mbtool: cannot open {path}: port busy (another program has it open)"
        holder.close()
        # Free again: mbtool opens it (and times out on the silent line).
        res = run_cli("read-holding-registers", "0", "-p", path, *PTY_SERIAL_OPTS, "-t", "0.3")
        assert res.returncode == 3, str(res)
    finally:
        stop.set()
        reader.join(timeout=2)
        holder.close()
        os.close(master)
        os.close(slave)
    assert len(received) == 8  # only the second run's request
