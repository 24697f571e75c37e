"""Poll groups in an inventory and in a map (issue 44): each group planned apart at its own
interval, the points in none at the device's; a hostile inventory is exit 2 naming the file, the
line and the key, with nothing opened."""

from __future__ import annotations

import math
import re

import pytest
from helpers.checks import assert_one_error_line, expect_ok
from helpers.exporter import exporting
from helpers.run import run_cli

from mbtool.plant.inventory import load_inventory
from mbtool.registermap.groups import DEFAULT, ONCE

MAP = (
    '[points.power]\nref = 40001\n[points.current]\nref = 40002\n[points.voltage]\nref = 40003\n'
    '[points.energy]\nref = 40011\ntype = "uint32"\n[points.serial]\nref = 40101\n'
)  # fmt: skip
LINK = '[poll]\ninterval = 10\n\n[links.gw]\ntarget = "tcp://127.0.0.1:{port}"\n\n'
DEVICE = '[devices.m]\nlink = "gw"\nmap = "meter.toml"\n'


def _inventory(tmp_path, port: int, device: str, map_text: str = MAP):
    (tmp_path / "meter.toml").write_text(map_text)
    path = tmp_path / "plant.toml"
    path.write_text(LINK.format(port=port) + DEVICE + device)
    return path


def _groups(spec) -> dict:
    return {
        group.name: (group.interval, [p.name for p in group.reader.points], len(group.reader.blocks))
        for group in spec.groups
    }


def test_a_devices_groups_each_have_their_reads_and_the_rest_keeps_the_devices_interval(tmp_path):
    path = _inventory(
        tmp_path, 1,
        'once = ["serial"]\n[devices.m.groups.fast]\ninterval = 1\npoints = ["power", "voltage"]\n'
        '[devices.m.groups.slow]\ninterval = 300\npoints = ["energy"]\n',
    )  # fmt: skip
    (spec,) = load_inventory(str(path)).devices
    assert _groups(spec) == {
        DEFAULT: (10.0, ["current"], 1),
        "fast": (1.0, ["power", "voltage"], 2),  # 40002 between them is another group's: two reads
        "slow": (300.0, ["energy"], 1),
        ONCE: (math.inf, ["serial"], 1),
    }
    assert [p.name for p in spec.reader.points] == ["power", "current", "voltage", "energy", "serial"]


def test_a_maps_groups_apply_to_the_points_a_device_reads_and_a_devices_own_replace_them(tmp_path):
    map_text = 'once = ["serial"]\n' + MAP + '[groups.fast]\ninterval = 2\npoints = ["power", "current"]\n'
    path = _inventory(tmp_path, 1, 'points = ["power", "energy", "serial"]\n', map_text)
    (spec,) = load_inventory(str(path)).devices
    assert _groups(spec) == {
        DEFAULT: (10.0, ["energy"], 1),
        "fast": (2.0, ["power"], 1),  # current: a point this device does not read
        ONCE: (math.inf, ["serial"], 1),
    }
    path = _inventory(
        tmp_path, 1, '[devices.m.groups.all]\ninterval = 5\npoints = ["power", "current"]\n', map_text
    )
    (spec,) = load_inventory(str(path)).devices
    assert _groups(spec) == {
        DEFAULT: (10.0, ["voltage", "energy", "serial"], 3),
        "all": (5.0, ["power", "current"], 1),
    }


def test_a_device_without_groups_has_none(tmp_path):
    (spec,) = load_inventory(str(_inventory(tmp_path, 1, ""))).devices
    assert spec.groups == () and [g.name for g in spec.paced()] == [DEFAULT]


@pytest.mark.parametrize(
    "device, line, words",
    [
        ('[devices.m.groups.fast]\ninterval = 1\npoints = ["power", "nope"]\n', 12, "[devices.m.groups.fast] points: no point named nope"),
        ('[devices.m.groups.a]\ninterval = 1\npoints = ["power"]\n[devices.m.groups.b]\ninterval = 2\npoints = ["power"]\n', 15, "[devices.m.groups.b] points: point power is in group a already"),
        ('[devices.m.groups.fast]\ninterval = 0\npoints = ["power"]\n', 11, "[devices.m.groups.fast] interval: expected seconds above 0"),
        ('[devices.m.groups.fast]\ninterval = -1\npoints = ["power"]\n', 11, "[devices.m.groups.fast] interval: expected seconds above 0"),
        ('once = ["power", "gone"]\n', 10, "[devices.m] once: no point named gone"),
        ('once = ["power"]\n[devices.m.groups.fast]\ninterval = 1\npoints = ["power"]\n', 10, "[devices.m] once: point power is in group fast already"),
        ('[devices.m.groups.fast]\ninterval = 1\npoints = ["power"]\ncolour = "red"\n', 13, "[devices.m.groups.fast] colour: unknown key"),
        ('groups.fast = { interval = "1", points = ["power"] }\n', 10, "[devices.m.groups.fast] interval: expected seconds"),
        ('[devices.m.groups.default]\ninterval = 1\npoints = ["power"]\n', 10, "[devices.m.groups.default]: a group's name"),
        ('[devices.m.groups.fast]\ninterval = 1\n', 10, "[devices.m.groups.fast] points: expected a list of point names"),
    ],
    ids=["unknown-point", "two-groups", "interval-0", "interval-negative", "once-unknown", "once-and-group",
         "unknown-key", "inline", "reserved-name", "no-points"],
)  # fmt: skip
def test_a_hostile_group_is_exit_2_naming_file_line_and_key_with_nothing_opened(
    tmp_path, silent_server, device, line, words
):
    path = _inventory(tmp_path, silent_server.port, device)
    error = assert_one_error_line(run_cli("poll", path, "--once"), 2)
    assert words in error and f"{path}:{line}: " in error, error
    assert silent_server.connections == 0


def test_groups_on_a_device_of_references_are_exit_2(tmp_path, silent_server):
    path = tmp_path / "plant.toml"
    path.write_text(
        LINK.format(port=silent_server.port)
        + '[devices.plc]\nlink = "gw"\nread = ["40001 4"]\n\n[devices.plc.groups.fast]\ninterval = 1\npoints = ["40001"]\n'
    )
    error = assert_one_error_line(run_cli("inventory", "check", path), 2)
    assert f"{path}:11: [devices.plc] groups: groups are of a map's points" in error, error
    assert silent_server.connections == 0


def test_a_hostile_group_in_a_map_is_exit_2_naming_the_map(tmp_path, silent_server):
    path = _inventory(
        tmp_path, silent_server.port, "", MAP + '[groups.fast]\ninterval = 1\npoints = ["watts"]\n'
    )
    error = assert_one_error_line(run_cli("inventory", "check", path), 2)
    assert "meter.toml: groups.fast.points: no point named watts" in error, error
    assert silent_server.connections == 0


SERIAL = '[links.bus1]\ntarget = "/dev/ttyMBTOOL-NONE"\nbaud = {baud}\nparity = "N"\n'
BIG_MAP = "".join(f"[points.r{n}]\nref = {40001 + n}\n" for n in range(100))


def _serial_plant(tmp_path, baud: int, extra: str = "") -> object:
    """100 registers every second on one serial link: two frames of 8 and 205 characters and
    two silences of 3.5, 10 bits a character (8N1)."""
    (tmp_path / "big.toml").write_text(BIG_MAP)
    path = tmp_path / "plant.toml"
    path.write_text(
        "[poll]\ninterval = 1\n" + SERIAL.format(baud=baud) + extra
        + '[devices.m]\nlink = "bus1"\nmap = "big.toml"\n'
    )  # fmt: skip
    return path


def test_check_prints_each_devices_groups_and_each_serial_links_budget(tmp_path, silent_server):
    path = _serial_plant(
        tmp_path, 9600, f'[links.gw]\ntarget = "tcp://127.0.0.1:{silent_server.port}"\n'
        '[devices.t]\nlink = "gw"\nmap = "big.toml"\nonce = ["r0"]\n',
    )  # fmt: skip
    path.write_text(path.read_text() + '[devices.m.groups.fast]\ninterval = 0.5\npoints = ["r0", "r1"]\n')
    out = expect_ok(run_cli("inventory", "check", path)).stdout
    assert (
        "    group default: 98 points, 1 read, every 1 s\n    group fast: 2 points, 1 read, every 0.5 s\n"
        in out
    )
    assert "    group once: 1 point, 1 read, at start and after each reconnect\n" in out
    char = 10 / 9600
    seconds = (8 + 5 + 196 + 7) * char + 2 * (8 + 5 + 4 + 7) * char  # the default group's read, fast's twice
    budget = re.search(
        r"  budget: bus1: the asked polls need ([\d.]+) s of line time a second at 9600 baud \(([\d.]+)%\), 3.0 reads/s\n",
        out,
    )
    assert budget and float(budget[1]) == pytest.approx(seconds, abs=0.001), out
    assert float(budget[2]) == pytest.approx(100 * seconds, abs=0.1)
    assert "link gw:" in out and "  budget: none, not a serial line of mbtool's own\n" in out
    assert silent_server.connections == 0


def test_a_link_asked_more_than_its_line_has_is_warned_of_and_refused_with_strict(tmp_path):
    path = _serial_plant(tmp_path, 1200)
    load = (8 + 205 + 7) * 10 / 1200  # 1.83 s of line time a second
    figures = f"bus1: the asked polls need {load:.3f} s of line time a second at 1200 baud ({load:.1%})"
    error = assert_one_error_line(run_cli("poll", path, "--once", "--strict"), 2)
    assert figures in error and "(--strict)" in error, error
    assert "cannot open" not in error  # refused before the port was opened
    result = run_cli("poll", path, "--once", "--stats", "json")
    assert result.returncode == 6  # without --strict it goes on (and finds no port)
    warning = result.stderr.splitlines()[0]
    assert warning.startswith(f"mbtool: warning: {figures}"), warning
    assert (
        expect_ok(run_cli("inventory", "check", _serial_plant(tmp_path, 9600))).stdout.count("budget:") == 1
    )


def test_prometheus_text_is_written_a_round_of_the_fastest_group_with_every_points_last_value(tmp_path):
    """-o prom writes the plant once a round of the fastest devices: a device's fastest group
    sets its pace, and each exposition holds the last value of every point of it."""
    (tmp_path / "meter.toml").write_text(MAP)
    path = tmp_path / "plant.toml"
    path.write_text(
        '[poll]\ninterval = 30\n[links.a]\ntarget = "sim://"\n[links.b]\ntarget = "sim://"\n'
        '[devices.m]\nlink = "a"\nmap = "meter.toml"\n[devices.m.groups.fast]\ninterval = 0.1\npoints = ["power"]\n'
        '[devices.n]\nlink = "b"\nmap = "meter.toml"\n'
    )
    out = expect_ok(run_cli("poll", path, "-o", "prom", "--duration", "1")).stdout
    expositions = out.split("# HELP modbus_up ")[1:]
    assert len(expositions) >= 5, out  # not one a 30 s round
    last = expositions[-1]
    for point in ("power", "current", "voltage", "energy", "serial"):
        assert f'modbus_{point}{{device="m"' in last, last


def test_the_exporter_warns_of_a_link_asked_more_than_its_line_has(tmp_path):
    path = _serial_plant(tmp_path, 1200)
    with exporting(path, tmp_path=tmp_path) as exporter:
        pass
    warning = exporter.stderr.read_text().splitlines()[0]
    assert warning.startswith(
        "mbtool: warning: bus1: the asked polls need 1.833 s of line time a second at 1200 baud"
    ), warning
