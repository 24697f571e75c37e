"""A map by name (issue 43): `-m sdm630`, an inventory's `map = "sdm630"` and an exporter's
module find the library's map; a map of the user's own (--maps DIR, the inventory's folder,
$XDG_CONFIG_HOME/mbtool/maps) comes first; a path is a path; an unknown name is one line."""

from __future__ import annotations

import fnmatch
import tomllib
from pathlib import Path

from helpers.checks import assert_one_error_line
from helpers.run import run_cli

from mbtool.cli.commands.exporter import Modules
from mbtool.library import MAPS, resolve_map
from mbtool.plant.inventory import load_inventory

OWN = "[points.own_point]\nref = 40001\n"


def request_lines(res) -> list[str]:
    return [line for line in res.stdout.splitlines() if line.startswith("raw ")]


def test_read_m_finds_the_library_map_by_name():
    res = run_cli("read", "-m", "sdm630", "--dry-run", "-p", "tcp://192.0.2.1")
    assert res.returncode == 0, res.stderr
    # the map's first read: input registers from 0 (FC 04)
    assert request_lines(res)[0].endswith("01 04 00 00 00 12")


def test_a_map_in_the_users_folder_shadows_the_librarys(tmp_path):
    folder = tmp_path / "mbtool" / "maps"
    folder.mkdir(parents=True)
    (folder / "sdm630.toml").write_text(OWN)
    res = run_cli(
        "read", "-m", "sdm630", "--dry-run", "-p", "tcp://192.0.2.1", env={"XDG_CONFIG_HOME": str(tmp_path)}
    )
    assert res.returncode == 0, res.stderr
    assert [line[-17:] for line in request_lines(res)] == ["01 03 00 00 00 01"]


def test_a_path_is_still_a_path():
    assert resolve_map("examples/energy-meter.toml") == Path("examples/energy-meter.toml")
    res = run_cli("read", "-m", "sdm630.toml", "--dry-run", "-p", "tcp://192.0.2.1")
    assert "cannot read map sdm630.toml" in assert_one_error_line(res, 2)


def test_an_unknown_name_is_one_line_with_the_nearest():
    line = assert_one_error_line(run_cli("read", "-m", "sdm63", "-p", "tcp://192.0.2.1"), 2)
    assert "no map named sdm63" in line and "nearest: sdm630" in line


def test_an_inventory_names_a_library_map_and_its_folder_comes_first(tmp_path):
    plant = tmp_path / "plant.toml"
    plant.write_text(
        '[links.bus]\ntarget = "tcp://192.0.2.1"\n'
        '[devices.meter]\nlink = "bus"\nunit = 1\nmap = "sdm630"\n'
        '[devices.other]\nlink = "bus"\nunit = 2\nmap = "mine"\n'
    )
    (tmp_path / "mine.toml").write_text(OWN)
    inventory = load_inventory(str(plant))
    assert inventory.maps == {"meter": str(MAPS / "sdm630.toml"), "other": str(tmp_path / "mine.toml")}


def test_the_exporters_modules_fall_back_to_the_library(tmp_path):
    (tmp_path / "sdm630.toml").write_text(OWN)
    assert Modules(None, {}).path_of("sdm630") == MAPS / "sdm630.toml"
    assert Modules(tmp_path, {}).path_of("sdm630") == tmp_path / "sdm630.toml"


def test_a_profile_names_a_library_map(tmp_path):
    config = tmp_path / "config.toml"
    config.write_text('[profiles.meter]\nport = "tcp://192.0.2.1"\nmap = "sdm630"\n')
    res = run_cli("read", "-P", "meter", "--dry-run", env={"MBTOOL_CONFIG": str(config)})
    assert res.returncode == 0, res.stderr
    assert request_lines(res)[0].endswith("01 04 00 00 00 12")


def test_the_package_ships_every_map_and_twin():
    """pyproject's package data names every file of the library (a wheel without them would
    know no map by name)."""
    globs = tomllib.loads((MAPS.parent.parent.parent / "pyproject.toml").read_text())["tool"]["setuptools"][
        "package-data"
    ]["mbtool.library"]
    files = [path.relative_to(MAPS.parent).as_posix() for path in MAPS.parent.rglob("*.toml")]
    assert len(files) >= 80
    assert [f for f in files if not any(fnmatch.fnmatch(f, glob) for glob in globs)] == []
