"""mbtool inventory check and split (issue 44): an inventory validated with nothing opened,
and split into one inventory a site, each a TOML file that loads (tomllib, then poll's loader)."""

from __future__ import annotations

import os
import tomllib

import pytest
from helpers.checks import assert_one_error_line, expect_ok
from helpers.run import REPO_ROOT, run_cli

from mbtool.plant.inventory import load_inventory

MAP = '[points.power]\nref = 40001\nunit = "W"\n'


@pytest.fixture
def plant(tmp_path, silent_server):
    """Two sites: a TCP gateway (nothing answers; nothing may connect) and two sim:// links,
    a map beside the inventory, a device by references."""
    (tmp_path / "maps").mkdir()
    (tmp_path / "maps" / "meter.toml").write_text(MAP)
    path = tmp_path / "plant.toml"
    path.write_text(
        '[poll]\ninterval = 5\n\n'
        f'[links.gw]\ntarget = "tcp://127.0.0.1:{silent_server.port}"\n'
        '[links.bus1]\ntarget = "sim://"\n[links.bus2]\ntarget = "sim://"\n\n'
        '[devices.m1]\nlink = "gw"\nmap = "maps/meter.toml"\ntags = { site = "north" }\n'
        '[devices.m2]\nlink = "bus1"\nmap = "maps/meter.toml"\ntags = { site = "north", room = "a b" }\n'
        '[devices."plc 3"]\nlink = "bus2"\nread = ["40001 4"]\nunit = 3\ntags = { site = "south" }\n'
    )  # fmt: skip
    return path


def test_check_prints_links_and_devices_and_opens_nothing(plant, silent_server):
    out = expect_ok(run_cli("inventory", "check", plant)).stdout
    assert out.splitlines()[0] == f"{plant}: 3 links, 3 devices"
    assert "link gw: tcp://127.0.0.1:" in out and "  plc 3: unit 3, 4 points (references), every 5 s" in out
    assert "  m1: unit 1, 1 point (map " in out
    assert silent_server.connections == 0 and silent_server.received_bytes() == b""


@pytest.mark.parametrize(
    "text, line, words",
    [
        ('[poll]\ninterval = 5\n[links.a]\ntarget = "sim://"\n[devices.d]\nlink = "a"\nread = ["40001"]\nspeed = 1\n', 8, "[devices.d] speed: unknown key"),
        ('[poll]\n\ncolour = "red"\n', 3, "[poll] colour: unknown key"),
        ('[links.a]\ntarget = "sim://"\n[devices.d]\nlink = "b"\nread = ["40001"]\n', 4, "[devices.d] link: no [links.b]"),
        ('[links.a]\ntarget = "tcp://127.0.0.1:{port}"\ntimeout = "fast"\n[devices.d]\nlink = "a"\nread = ["40001"]\n', 3, "[links.a] timeout"),
        ('[links.a]\ntarget = "sim://"\n[devices.d]\nlink = "a"\nmap = "../../../../etc/passwd"\n', 5, "[devices.d] map"),
        ("[links.a\n", 1, "not valid TOML"),
        ('[links.a]\ntarget = "sim://"\n[devices.d]\nlink = "a"\nread = ["40001"]\ntags = {{ site = "x\\ny" }}\n', 6, "[devices.d] tags.site"),
    ],
    ids=["unknown-key", "poll-key", "missing-link", "bad-timeout", "map-outside", "toml", "control-char"],
)  # fmt: skip
def test_check_of_a_hostile_inventory_is_exit_2_with_the_line_and_key(
    tmp_path, silent_server, text, line, words
):
    path = tmp_path / "plant.toml"
    path.write_text(text.format(port=silent_server.port))
    error = assert_one_error_line(run_cli("inventory", "check", path), 2)
    assert words in error, error
    if words != "not valid TOML":
        assert f"{path}:{line}: " in error, error
    else:
        assert "line 1" in error, error
    assert silent_server.connections == 0


def test_split_by_site_writes_one_loadable_inventory_a_site(plant, tmp_path):
    out = tmp_path / "sites"
    expect_ok(run_cli("inventory", "split", plant, "--by", "tag:site", "-o", out))
    assert sorted(p.name for p in out.iterdir()) == ["north.toml", "south.toml"]
    north = tomllib.loads((out / "north.toml").read_text())
    assert set(north["links"]) == {"gw", "bus1"} and set(north["devices"]) == {"m1", "m2"}
    assert north["poll"] == {"interval": 5} and north["devices"]["m2"]["tags"] == {
        "site": "north",
        "room": "a b",
    }
    south = tomllib.loads((out / "south.toml").read_text())
    assert set(south["links"]) == {"bus2"} and south["devices"]["plc 3"]["read"] == ["40001 4"]
    loaded = load_inventory(str(out / "north.toml"))  # its maps resolve from the new folder
    assert [d.name for d in loaded.devices] == ["m1", "m2"] and loaded.maps["m1"] == str(
        tmp_path / "maps" / "meter.toml"
    )
    expect_ok(run_cli("inventory", "check", out / "south.toml"))


@pytest.mark.parametrize(
    "change, words",
    [
        (('tags = { site = "south" }', "tags = { room = 1 }"), "[devices.plc 3] has no tag site"),
        (('tags = { site = "south" }', 'tags = { site = "../x" }'), "cannot name a file"),
        (('link = "bus2"', 'link = "bus1"'), "[links.bus1] has devices of site north and south"),
    ],
    ids=["untagged", "path", "link-in-two-sites"],
)
def test_a_bad_split_is_exit_2_with_nothing_written(plant, tmp_path, change, words):
    plant.write_text(plant.read_text().replace(*change))
    out = tmp_path / "sites"
    line = assert_one_error_line(run_cli("inventory", "split", plant, "--by", "tag:site", "-o", out), 2)
    assert words in line and not out.exists()


def test_split_by_something_else_than_a_tag_is_exit_2(plant, tmp_path):
    line = assert_one_error_line(
        run_cli("inventory", "split", plant, "--by", "site", "-o", tmp_path / "o"), 2
    )
    assert "expected tag:NAME" in line


def test_a_split_of_an_inventory_named_relatively_names_its_maps_absolutely(plant, tmp_path):
    """The maps of an inventory given by a relative path (the usual `inventory split plant.toml`)
    resolve from the current folder; each part names them absolutely, so a part loads from its
    own folder."""
    relative = os.path.relpath(plant, REPO_ROOT)  # run_cli runs in the repository
    expect_ok(run_cli("inventory", "split", relative, "--by", "tag:site", "-o", tmp_path / "sites"))
    north = tmp_path / "sites" / "north.toml"
    assert tomllib.loads(north.read_text())["devices"]["m1"]["map"] == str(tmp_path / "maps" / "meter.toml")
    expect_ok(run_cli("inventory", "check", north))
