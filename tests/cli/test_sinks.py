"""One sink per output format behind one registry (issue 41, point 2).

Each format of -o is a module of mbtool/cli/sinks/, named in the registry
(``mbtool.cli.sinks.SINKS``) by one line; every -o choice is the registry's; rich is drawn
by the table sink alone; no module borrows another's private helpers; and a new format
is one file and one line: a copy of the tree with a tsv sink added reads with -o tsv.
"""

from __future__ import annotations

import ast
import importlib
import shutil
import subprocess
import sys
from pathlib import Path

import click
import pytest
from helpers.run import run_cli

from mbtool.cli import sinks
from mbtool.cli.program import COMMANDS

ROOT = Path(__file__).resolve().parent.parent.parent
PACKAGE = ROOT / "mbtool"


def _command(name: str) -> click.Command:
    return getattr(importlib.import_module(f"mbtool.cli.commands.{COMMANDS[name]}"), name.replace("-", "_"))


def _format_choices(command: click.Command) -> tuple[str, ...] | None:
    for param in command.params:
        if param.name == "output_format":
            return tuple(param.type.choices)
    return None


def test_every_format_choice_is_the_registrys():
    kinds = {kind for sink in sinks.SINKS.values() for kind in sink.kinds}
    offered = {kind: sinks.formats(kind) for kind in kinds}
    seen = 0
    for name in COMMANDS:
        choices = _format_choices(_command(name))
        if choices is None:
            continue
        seen += 1
        assert choices in offered.values() or choices == sinks.formats(sinks.RESULTS, sinks.READINGS), (
            name,
            choices,
        )
    assert seen >= 30  # the device commands, the offline ones, monitor, bridge, poll
    assert _format_choices(_command("read")) == ("table", "plain", "json", "csv", "influx", "prom")
    assert _format_choices(_command("poll")) == sinks.formats(sinks.PLANT)


def test_an_inventory_takes_the_formats_poll_offers(tmp_path):
    plant = tmp_path / "plant.toml"
    plant.write_text(
        '[poll]\noutput = "yaml"\n[links.l]\ntarget = "sim://"\n[devices.d]\nlink = "l"\nunit = 1\nread = ["40001 1"]\n'
    )
    res = run_cli("poll", str(plant), "--once")
    assert res.returncode == 2 and res.stdout == "", res
    assert f"'yaml' is not one of {', '.join(sinks.formats(sinks.PLANT))}" in res.stderr, res


def test_each_format_is_a_module_of_its_own():
    files = {path.stem for path in (PACKAGE / "cli" / "sinks").glob("*.py")} - {"__init__"}
    assert files == set(sinks.SINKS)
    for name in sinks.SINKS:
        assert sinks.sink(name).__name__ == f"mbtool.cli.sinks.{name}"


def _imports(path: Path):
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            yield from ((alias.name, None) for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module:
            yield from ((node.module, alias.name) for alias in node.names)


def test_rich_is_drawn_by_the_table_sink_alone():
    users = sorted(
        str(path.relative_to(ROOT))
        for path in PACKAGE.rglob("*.py")
        if any(module.split(".")[0] == "rich" for module, _ in _imports(path))
    )
    assert users == ["mbtool/cli/sinks/table.py"]


def test_no_module_of_the_cli_borrows_another_modules_private_names():
    # plant_text.py took five of metrics.py's: the Prometheus text is the prom sink's, public.
    borrowed = sorted(
        f"{path.relative_to(ROOT)}: {module}.{name}"
        for path in (PACKAGE / "cli").rglob("*.py")
        for module, name in _imports(path)
        if module.startswith("mbtool") and name and name.startswith("_") and not name.startswith("__")
    )
    assert borrowed == []


def test_no_format_is_told_by_its_name_outside_the_sinks():
    # fmt == "json" chains: a format's behaviour is its sink's, not a comparison in a command
    # (47 in 13 modules before the sinks).
    found = []
    for path in (PACKAGE / "cli").rglob("*.py"):
        if "sinks" in path.relative_to(PACKAGE).parts:
            continue
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Compare):
                names = [node.left, *node.comparators]
                told = [n.value for n in names if isinstance(n, ast.Constant) and n.value in sinks.SINKS]
                if told and any("fmt" in ast.unparse(n) or "format" in ast.unparse(n) for n in names):
                    found.append(f"{path.relative_to(ROOT)}:{node.lineno}: {ast.unparse(node)}")
    assert found == []


TSV = '''"""-o tsv: tab-separated values, a row a value."""

from mbtool.cli.sinks.csv import rows_of


def render(result, out, csv_header=True):
    header, rows = rows_of(result)
    out.write("".join("\\t".join(row) + "\\n" for row in ([header] if header and csv_header else []) + rows))
'''


@pytest.mark.timeout(60)
def test_a_new_format_is_one_file_and_one_line(tmp_path):
    shutil.copytree(PACKAGE, tmp_path / "mbtool", ignore=shutil.ignore_patterns("__pycache__"))
    (tmp_path / "mbtool" / "cli" / "sinks" / "tsv.py").write_text(TSV)
    registry = tmp_path / "mbtool" / "cli" / "sinks" / "__init__.py"
    text = registry.read_text()
    line = '    Sink("csv",'
    assert text.count(line) == 1
    registry.write_text(text.replace(line, '    Sink("tsv", "tab-separated values", {RESULTS}),\n' + line))
    res = subprocess.run(
        [sys.executable, "-m", "mbtool", "read-holding-registers", "0", "2", "-p", "sim://", "-o", "tsv"],
        cwd=tmp_path,
        env={"PYTHONPATH": str(tmp_path), "PATH": "/usr/bin:/bin"},
        capture_output=True,
        text=True,
        timeout=30,
    )
    assert res.returncode == 0, res.stderr
    assert res.stdout == "address\tvalue\n0\t0\n1\t1\n"
