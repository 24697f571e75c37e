"""mbtool poll's inventory, checked whole before anything is opened (issue 31), in-process: a bad
one is exit 2 with one line naming the file, the table and the key."""

from __future__ import annotations

import pytest
from helpers import (
    assert_one_error_line,
    run_cli,
)


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
        ('measurement = "#meters"', ["-o", "influx"], "[devices.d] measurement: a line starting with # is a comment"),
        ('measurement = ""', ["-o", "influx"], "[devices.d] measurement: a measurement has a name"),
        ("measurement = 3", ["-o", "influx"], "[devices.d] measurement: expected"),
        ("", ["-o", "influx", "--measurement", "a\\"], "--measurement 'a\\\\': a backslash at the end"),
        ("", ["-o", "prom", "--measurement", "plant"], "--measurement names InfluxDB's measurement"),
    ],
    ids=["comment", "empty", "number", "backslash", "not-influx"],
)
def test_a_measurement_influx_cannot_carry_is_exit_2_with_nothing_opened(tmp_path, silent_server, key, args, words):
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
