"""poll's live view counts in words that agree with their numbers (a new user's walk found
'1 devices' in its title; issue 39 item 21)."""

from __future__ import annotations

from rich.console import Console

from mbtool.cli.commands.poll import LiveView
from mbtool.cli.program import register_schemes
from mbtool.codec.record import replace
from mbtool.plant.inventory import load_inventory
from mbtool.plant.schedule import DeviceState


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
