"""mbtool poll's inventory, checked whole before anything is opened (issue 31), in-process: a bad
one is exit 2 with one line naming the file, the table and the key."""

from __future__ import annotations

import pytest
from helpers.checks import assert_one_error_line
from helpers.run import run_cli

from mbtool.cli.program import register_schemes
from mbtool.plant.inventory import load_inventory


@pytest.mark.parametrize(
    "text, words",
    [
        ("[poll]\ninterval = 1\ncolour = 1\n", "[poll] colour: unknown key"),
        ("[plant]\n", "unknown table [plant]"),
        ('[links.a]\ntarget = "{t}"\nbaud = "fast"\n[devices.d]\nlink = "a"\nread = ["40001"]\n', "[links.a] baud"),
        ('[links.a]\nbaud = 9600\n[devices.d]\nlink = "a"\nread = ["40001"]\n', "[links.a] has no target"),
        ('[links.a]\ntarget = "{t}"\n[devices.d]\nlink = "b"\nread = ["40001"]\n', "[devices.d] link: no [links.b]"),
        ('[links.a]\ntarget = "{t}"\n[devices.d]\nlink = "a"\nread = ["40001"]\nspeed = 1\n', "[devices.d] speed: unknown key"),
        ('[links.a]\ntarget = "{t}"\n[devices.d]\nlink = "a"\nmap = "nosuch.toml"\n', "[devices.d] map: cannot read map"),
        ('[links.a]\ntarget = "{t}"\n[devices.d]\nlink = "a"\n', "[devices.d]: give either map"),
        ('[links.a]\ntarget = "{t}"\n[devices.d]\nlink = "a"\nread = ["4o001 2"]\n', "[devices.d] read: '4o001 2'"),
        ('[links.a]\ntarget = "{t}"\n[devices.d]\nlink = "a"\nread = ["40001"]\ntags = {{ "a-b" = "x" }}\n', "tags: 'a-b'"),
        ('[links.a]\ntarget = "{t}"\n[devices.d]\nlink = "a"\nread = ["40001"]\nunit = 300\n', "[devices.d] unit"),
        ('[links.a]\ntarget = "{t}"\n[devices.d]\nlink = "a"\nread = ["40001"]\n[devices.d]\nunit = 2\n', "not valid TOML"),
        ("[poll]\ninterval = 1\n", "no [devices.NAME]"),
    ],
    ids=[
        "poll-key", "table", "link-value", "no-target", "missing-link", "device-key", "map",
        "map-or-read", "reference", "tag-name", "unit", "two-devices-one-name", "no-devices",
    ],
)  # fmt: skip
def test_a_bad_inventory_is_exit_2_naming_file_table_and_key_and_nothing_is_opened(
    tmp_path, silent_server, text, words
):
    path = tmp_path / "plant.toml"
    path.write_text(text.format(t=silent_server.socket_target.replace("socket", "tcp")))
    line = assert_one_error_line(run_cli("poll", path, "--once"), 2)
    assert str(path) in line and words in line
    assert silent_server.received_bytes() == b""


@pytest.mark.parametrize(
    "output", [["-o", "prom"], ["--textfile", "{dir}/plant.prom"]], ids=["prom", "textfile"]
)
def test_a_point_named_as_a_devices_own_metric_is_refused_for_prometheus_text(
    tmp_path, silent_server, output
):
    """A point `up` would be modbus_up, the family that says whether the device answered:
    with -o prom or --textfile that is two families of one name, refused before anything is
    opened; other outputs name the point as it is."""
    (tmp_path / "map.toml").write_text("[points.up]\nref = 40001\n")
    path = tmp_path / "plant.toml"
    target = silent_server.socket_target.replace("socket", "tcp")
    path.write_text(f'[links.a]\ntarget = "{target}"\n[devices.d]\nlink = "a"\nmap = "map.toml"\n')
    args = [part.format(dir=tmp_path) for part in output]
    line = assert_one_error_line(run_cli("poll", path, "--once", *args), 2)
    assert str(path) in line and "point up: its metric, modbus_up" in line and "rename the point" in line
    assert silent_server.received_bytes() == b"" and not (tmp_path / "plant.prom").exists()


@pytest.mark.parametrize(
    "key, args, words",
    [
        (
            'measurement = "#meters"',
            ["-o", "influx"],
            "[devices.d] measurement: a line starting with # is a comment",
        ),
        ('measurement = ""', ["-o", "influx"], "[devices.d] measurement: a measurement has a name"),
        ("measurement = 3", ["-o", "influx"], "[devices.d] measurement: expected"),
        ("", ["-o", "influx", "--measurement", "a\\"], "--measurement 'a\\\\': a backslash at the end"),
        ("", ["-o", "prom", "--measurement", "plant"], "--measurement names InfluxDB's measurement"),
    ],
    ids=["comment", "empty", "number", "backslash", "not-influx"],
)
def test_a_measurement_influx_cannot_carry_is_exit_2_with_nothing_opened(
    tmp_path, silent_server, key, args, words
):
    path = tmp_path / "plant.toml"
    target = silent_server.socket_target.replace("socket", "tcp")
    path.write_text(f'[links.a]\ntarget = "{target}"\n[devices.d]\nlink = "a"\nread = ["40001"]\n{key}\n')
    line = assert_one_error_line(run_cli("poll", path, "--once", *args), 2)
    assert words in line, line
    assert silent_server.received_bytes() == b""


def test_a_point_named_value_beside_a_device_of_raw_registers_is_refused_for_prometheus_text(
    tmp_path, silent_server
):
    """modbus_value is the family of the registers a device's read lists: a map point `value`
    beside such a device would be a second family of that name."""
    (tmp_path / "map.toml").write_text("[points.value]\nref = 40001\n")
    path = tmp_path / "plant.toml"
    target = silent_server.socket_target.replace("socket", "tcp")
    path.write_text(
        f'[links.a]\ntarget = "{target}"\n[devices.m]\nlink = "a"\nmap = "map.toml"\n'
        '[devices.r]\nlink = "a"\nread = ["40001 2"]\n'
    )
    line = assert_one_error_line(run_cli("poll", path, "--once", "-o", "prom"), 2)
    assert "[devices.m] map: point value: its metric, modbus_value" in line
    assert silent_server.received_bytes() == b""


@pytest.mark.parametrize(
    "first, second",
    [
        ("tcp://127.0.0.1:{port}", "tcp://127.0.0.1:{port}/"),
        ("tcp://127.0.0.1:{port}", "socket://127.0.0.1:{port}"),  # RTU over the same TCP port
        ("tcp://[::ffff:127.0.0.1]:{port}", "tls://[0:0:0:0:0:ffff:7f00:1]:{port}"),
        ("tcp://Plc7.Example:{port}", "tcp://plc7.example.:{port}"),
        ("{dir}/ttyUSB0", "{dir}/by-id/usb-FTDI-if00"),  # a serial port and a link to it
    ],
    ids=["same", "socket", "ipv6-spellings", "host-case", "serial-symlink"],
)
def test_two_links_on_one_target_are_refused_naming_both(tmp_path, silent_server, first, second):
    """A serial port opens once (the second link's devices would never be polled: port busy,
    by mbtool itself), and two links to one TCP device are two masters polling it at once:
    refused at load, exit 2, naming both links, with nothing opened."""
    (tmp_path / "ttyUSB0").write_text("")
    (tmp_path / "by-id").mkdir()
    (tmp_path / "by-id" / "usb-FTDI-if00").symlink_to(tmp_path / "ttyUSB0")
    targets = [t.format(port=silent_server.port, dir=tmp_path) for t in (first, second)]
    path = tmp_path / "plant.toml"
    path.write_text(
        f'[links.bus1]\ntarget = "{targets[0]}"\n[links.bus2]\ntarget = "{targets[1]}"\n'
        '[devices.a]\nlink = "bus1"\nread = ["40001"]\n[devices.b]\nlink = "bus2"\nread = ["40001"]\n'
    )
    line = assert_one_error_line(run_cli("poll", path, "--once"), 2)
    assert str(path) in line and "[links.bus1]" in line and "[links.bus2]" in line, line
    assert silent_server.received_bytes() == b""


def test_links_on_different_targets_and_in_process_devices_load(tmp_path, silent_server):
    """Not one target: UDP and TCP on one port number, two sim:// links (each a device of its own)."""
    register_schemes()  # sim://, as main registers it
    path = tmp_path / "plant.toml"
    path.write_text(
        f'[links.a]\ntarget = "tcp://127.0.0.1:{silent_server.port}"\n'
        f'[links.b]\ntarget = "udp://127.0.0.1:{silent_server.port}"\n'
        '[links.c]\ntarget = "sim://"\n[links.d]\ntarget = "sim://"\n'
        + "".join(f'[devices.{n}]\nlink = "{n}"\nread = ["40001"]\n' for n in "abcd")
    )
    assert len(load_inventory(str(path)).links) == 4


@pytest.mark.parametrize(
    "poll, device, words",
    [
        ("max_backoff = 0.5\n", "interval = 2\n", "[devices.d] max_backoff: 0.5 s (from [poll]) is below its interval, 2 s"),
        ("", "interval = 2\nmax_backoff = 1\n", "[devices.d] max_backoff: 1 s is below its interval, 2 s"),
        ("interval = 60\nmax_backoff = 30\n", "", "[devices.d] max_backoff: 30 s (from [poll]) is below its interval, 60 s"),
    ],
    ids=["poll", "device", "both-from-poll"],
)  # fmt: skip
def test_a_max_backoff_below_the_interval_is_refused(tmp_path, silent_server, poll, device, words):
    """An offline device tried more often than an online one is polled: thousands of reconnects
    a second (issue 40.19); refused at load, exit 2, nothing opened."""
    path = tmp_path / "plant.toml"
    path.write_text(
        f'[poll]\n{poll}[links.a]\ntarget = "{silent_server.tcp_target}"\n'
        f'[devices.d]\nlink = "a"\nread = ["40001"]\n{device}'
    )
    line = assert_one_error_line(run_cli("poll", path, "--once"), 2)
    assert str(path) in line and words in line, line
    assert silent_server.received_bytes() == b""


def test_the_default_max_backoff_is_never_below_the_interval(tmp_path):
    """A device polled once an hour, max_backoff left out: backed off an hour at the least, not
    the default 300 s (which would poll an offline device more often than an online one)."""
    path = tmp_path / "plant.toml"
    path.write_text(
        '[links.a]\ntarget = "tcp://127.0.0.1:1"\n[devices.slow]\nlink = "a"\nread = ["40001"]\ninterval = 3600\n'
        '[devices.fast]\nlink = "a"\nunit = 2\nread = ["40001"]\ninterval = 2\n'
    )
    devices = {d.name: d for d in load_inventory(str(path)).devices}
    assert devices["slow"].max_backoff == 3600 and devices["fast"].max_backoff == 300


@pytest.mark.parametrize(
    "where", ["{dir}/nosuch/plant.prom", "{dir}/plant.toml/plant.prom"], ids=["missing", "not-a-folder"]
)
def test_a_textfile_that_cannot_be_written_is_exit_7_before_any_link_is_opened(
    tmp_path, silent_server, where
):
    """--textfile in a folder that is not there, or is a file: found before any device is
    polled (and before a dead one's timeout), as dump finds its file (issue 39.17)."""
    path = tmp_path / "plant.toml"
    path.write_text(
        f'[links.a]\ntarget = "{silent_server.tcp_target}"\n[devices.d]\nlink = "a"\nread = ["40001"]\n'
    )
    textfile = where.format(dir=tmp_path)
    line = assert_one_error_line(run_cli("poll", path, "--once", "--textfile", textfile), 7)
    assert textfile in line, line
    assert silent_server.received_bytes() == b"" and silent_server.connections == 0


@pytest.mark.parametrize(
    "key, value", [("cert", "5"), ("baud", '"9600"'), ("echo", '"yes"'), ("framer", "5"), ("parity", '"X"')]
)
def test_a_links_key_is_read_as_a_profiles_key_is(tmp_path, key, value):
    """Issue 41.3: one reading of a link setting, from the table of them: an inventory's link
    says of a value what a profile says of it (cert = 5 was an internal error, exit 1; baud =
    "9600" was taken by one and refused by the other)."""
    inventory = tmp_path / "plant.toml"
    inventory.write_text(
        f'[links.a]\ntarget = "sim://"\n{key} = {value}\n[devices.d]\nlink = "a"\nread = ["40001"]\n'
    )
    config = tmp_path / "config.toml"
    config.write_text(f'[profiles.s]\nport = "sim://"\n{key} = {value}\n')
    polled = assert_one_error_line(run_cli("poll", str(inventory), "--once"), 2)
    read = assert_one_error_line(run_cli("read-coils", "0", "-P", "s", env={"MBTOOL_CONFIG": str(config)}), 2)
    said = read.split(f"profiles.s.{key}: ", 1)[1]
    assert polled == f"mbtool: {inventory}: [links.a] {key}: {said}"
