"""poll's live view counts in words that agree with their numbers (a new user's walk found
'1 devices' in its title; issue 39 item 21)."""

from __future__ import annotations

import re

from rich.console import Console

from mbtool.cli.commands.poll import LiveView
from mbtool.cli.program import register_schemes
from mbtool.codec.record import replace
from mbtool.plant.inventory import load_inventory
from mbtool.plant.schedule import DeviceState, Plant


def screen_of(tmp_path, devices: int, rows: int) -> str:
    register_schemes()  # sim://, as mbtool's main registers it
    plant = tmp_path / "plant.toml"
    plant.write_text(
        '[links.bus]\ntarget = "sim://"\n'
        + "".join(
            f'[devices.d{n}]\nlink = "bus"\nunit = {n + 1}\nread = ["40001 1"]\n' for n in range(devices)
        )
    )
    view = LiveView(replace(load_inventory(str(plant)), path="plant.toml"), clock=lambda: 0.0)
    view.states = {spec.name: DeviceState(spec, 0.0) for spec in view.plant.devices}
    console = Console(width=100, height=rows, record=True, color_system=None)
    console.print(view)
    return console.export_text()


def test_the_title_counts_one_device_in_the_singular(tmp_path):
    assert "plant.toml: 1 device, 0 online, 0 offline" in screen_of(tmp_path, 1, 30).splitlines()[0]


def test_a_device_of_poll_groups_shows_every_points_last_value_and_each_groups_pace(tmp_path):
    """Issue 44: each group's poll carries its own points; the row keeps the last value of every
    point, and a column says each group's achieved and asked interval."""
    register_schemes()
    (tmp_path / "m.toml").write_text("[points.power]\nref = 40001\n[points.energy]\nref = 40011\n")
    plant = tmp_path / "plant.toml"
    plant.write_text(
        '[poll]\ninterval = 0.1\n[links.bus]\ntarget = "sim://"\n[devices.m]\nlink = "bus"\nmap = "m.toml"\n'
        '[devices.m.groups.fast]\ninterval = 0.05\npoints = ["power"]\n'
    )
    view = LiveView(replace(load_inventory(str(plant)), path="plant.toml"), clock=lambda: 0.0)
    Plant(view.plant.links, view.plant.devices, view.report, rounds=3).run()
    console = Console(width=160, height=12, record=True, color_system=None)
    console.print(view)
    text = console.export_text()
    assert "groups: achieved/asked s" in text
    row = next(line for line in text.splitlines() if line.startswith("m "))
    assert "power=" in row and "energy=" in row, row  # the fast group's poll came last
    # a poll late on a busy machine adds "(N late)" after its group's pace
    assert re.search(r"fast 0\.\d\d/0\.05( \(\d+ late\))?, default 0\.\d\d/0\.1\b", row), row
