"""SunSpec's model definitions (mbtool/sunspec/models/): the SunSpec Alliance's, as pysunspec2 ships
them, in the wheel, each laid out as a register map the loader takes; the twin and the quirk files
as the script makes them; and mbtool sunspec's checks before anything is sent, in-process (issue 34).
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from helpers.run import REPO_ROOT, run_cli

from mbtool.registermap.load import build_map
from mbtool.sunspec.layout import lay_out, map_rows
from mbtool.sunspec.models import MODELS, definition, known_models, point_size


def test_the_model_definitions_are_pysunspec2s_unchanged_with_their_license():
    import sunspec2

    theirs = Path(sunspec2.__file__).parent / "models" / "json"
    ours = sorted(path.name for path in MODELS.glob("model_*.json"))
    assert ours == sorted(path.name for path in theirs.glob("model_*.json"))
    assert len(ours) > 100
    for name in ours:
        assert (MODELS / name).read_bytes() == (theirs / name).read_bytes(), name
    assert "Apache License" in (MODELS / "LICENSE").read_text()


def test_the_definitions_ship_in_the_wheel():
    """package data: a pip install has the JSON files, not only a checkout."""
    import tomllib

    config = tomllib.loads((REPO_ROOT / "pyproject.toml").read_text())
    data = config["tool"]["setuptools"]["package-data"]["mbtool.sunspec"]
    assert "models/*.json" in data and "models/LICENSE" in data


def test_every_model_sunspec_defines_lays_out_as_a_register_map():
    """Each of the 112 definitions, its repeating groups twice, its counts 1, is a map the
    loader takes, a point for each point (but the ones no map type carries)."""
    for model_id in known_models():
        group = definition(model_id)
        fixed = sum(point_size(point) for point in group["points"])
        layout = lay_out(model_id, group["name"], 20000, [1] * (fixed + 600))
        rows, left_out = map_rows(layout)
        points = build_map(f"model {model_id}", {}, rows).points if rows else {}
        slots = list(layout.root.every_slot())
        assert len(points) + len(left_out) == len(slots), model_id
        for slot in slots:
            assert slot.size == point_size(slot.point)


def test_the_twin_and_the_quirk_files_are_what_the_script_makes():
    res = subprocess.run(
        [sys.executable, "scripts/make_sunspec_twin.py", "--check"],
        cwd=REPO_ROOT,
        capture_output=True,
        text=True,
    )
    assert res.returncode == 0, res.stderr


def test_dry_run_shows_the_first_read_and_sends_nothing():
    res = run_cli("sunspec", "-p", "tcp://127.0.0.1:9", "--dry-run")
    assert res.returncode == 0, res
    assert "Read Holding Registers" in res.stdout and "40000" in res.stdout
    assert "then the chain of models after the marker" in res.stderr


def test_map_must_be_a_toml_file_name_before_anything_is_sent():
    res = run_cli("sunspec", "-p", "tcp://127.0.0.1:9", "--map", "inverter.csv")
    assert res.returncode == 2
    assert "--map writes a TOML map: inverter.csv is not a .toml file name" in res.stderr


def test_the_layouts_warnings_count_in_words_that_agree():
    """Issue 39 item 21: one register is "1 register ... is", not "1 registers ... are"."""
    common = definition(1)
    fixed = sum(point_size(point) for point in common["points"]) - 2  # less the id and length
    assert lay_out(64999, "model_64999", 40070, [7]).warnings == (
        "model 64999 at 40070: SunSpec defines no model 64999: its 1 register is shown raw",
    )
    assert lay_out(1, "common", 40002, [0] * (fixed + 1)).warnings == (
        f"model 1 at 40002 (common): {fixed + 1} registers on the wire, {fixed} in its definition; the "
        "length on the wire is used: the 1 register past the definition is shown raw",
    )
    mppt = definition(160)
    head = sum(point_size(point) for point in mppt["points"]) - 2
    module = sum(point_size(point) for point in mppt["groups"][0]["points"])
    (warning,) = lay_out(160, "mppt", 40070, [0] * (head + module + 1)).warnings
    assert warning.endswith(
        f"1 register after 1 module group ({module} registers each) does not make another: shown raw"
    ), warning
