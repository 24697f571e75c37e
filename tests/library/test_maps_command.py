"""`mbtool maps list` and `mbtool maps show` (issue 43): the library as a user browses it."""

from __future__ import annotations

import json

from helpers.checks import assert_one_error_line
from helpers.run import run_cli

import mbtool.link.transport
from mbtool.library import MAPS, library_names


def test_list_names_every_map_with_its_device_and_source():
    res = run_cli("maps", "list")
    assert res.returncode == 0, res.stderr
    assert res.lines[0].split() == ["NAME", "MANUFACTURER", "MODEL", "KIND", "TRANSPORT", "SOURCE"]
    listed = [line.split()[0] for line in res.lines[1:]]
    assert listed == library_names()
    sdm630 = next(line for line in res.lines if line.startswith("sdm630 "))
    assert "Eastron" in sdm630 and "meter" in sdm630 and "Modbus Protocol" in sdm630


def test_list_json_and_a_search():
    res = run_cli("maps", "list", "--json", "EASTRON")
    rows = json.loads(res.stdout)
    assert rows and all(row["manufacturer"] == "Eastron" for row in rows)
    assert set(rows[0]) == {"name", "manufacturer", "model", "kind", "transport", "source"}
    assert json.loads(run_cli("maps", "list", "--json", "no such device").stdout) == []


def test_show_prints_the_device_its_signature_and_points():
    res = run_cli("maps", "show", "sdm630")
    assert res.returncode == 0, res.stderr
    assert res.lines[0].startswith("Eastron SDM630")
    assert "signature: 30001 float32 in 80..300" in res.lines
    row = next(line for line in res.lines if line.startswith("energy_import "))
    assert row.split() == ["energy_import", "30073", "float32", "ABCD", "kWh", "r"]


def test_show_toml_is_the_file():
    assert run_cli("maps", "show", "sdm630", "--toml").stdout == (MAPS / "sdm630.toml").read_text()


def test_show_of_an_unknown_name_is_one_line():
    assert "no map named sdm6300" in assert_one_error_line(run_cli("maps", "show", "sdm6300"), 2)


def test_identify_refuses_the_bus_walks_options_without_all_units():
    line = assert_one_error_line(run_cli("identify", "--inventory", "plant.toml", "-p", "tcp://192.0.2.1"), 2)
    assert "--inventory goes with --all-units" in line


def test_a_dry_run_of_a_bus_walk_shows_its_first_probe_and_opens_nothing(monkeypatch):
    def refuse(*args, **kwargs):
        raise AssertionError("a dry run opened the port")

    monkeypatch.setattr(mbtool.link.transport, "open_transport", refuse)
    res = run_cli(
        "identify", "--all-units", "--units", "3-5", "--dry-run", "-p", "/dev/ttyUSB0", "-o", "plain"
    )
    assert res.returncode == 0, res
    assert res.lines[0] == "raw 03 03 00 00 00 01 85 E8"  # unit 3, FC 03 holding register 0
    assert "then the same read to units 4-5" in res.stderr
