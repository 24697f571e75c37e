"""The rooms by role (issue 14): import-linter's contracts in pyproject.toml hold, and they bite.

The contracts are import-linter's own, run by its own command; these tests run it on
the tree as it is, and on a copy with one forbidden import or one cycle added, which
must break the contract that forbids it.  Ruff's rules in pyproject.toml hold too (issue
30): imports at the top of the module (PLC0415) but for the few that say why not, and the
code as ruff format writes it.  And the map is current (issue 41): ARCHITECTURE.md names every
module of mbtool/, and no file that is gone.
"""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
LINT = [
    sys.executable,
    "-c",
    "import sys; from importlinter.cli import lint_imports_command; sys.exit(lint_imports_command())",
]

pytestmark = pytest.mark.timeout(120)


def lint(where: Path) -> subprocess.CompletedProcess:
    return subprocess.run(
        [*LINT, "--config", str(where / "pyproject.toml"), "--no-cache"],
        cwd=where,
        env={"PYTHONPATH": str(where), "PATH": "/usr/bin:/bin"},
        capture_output=True,
        text=True,
        timeout=100,
    )


def test_the_tree_keeps_every_contract():
    res = lint(ROOT)
    assert res.returncode == 0, res.stdout + res.stderr
    assert "BROKEN" not in res.stdout and " kept, 0 broken" in res.stdout


@pytest.fixture
def copy(tmp_path):
    shutil.copytree(ROOT / "mbtool", tmp_path / "mbtool", ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copy(ROOT / "pyproject.toml", tmp_path / "pyproject.toml")
    return tmp_path


def _add_to_function(path: Path, line: str) -> None:
    path.write_text(path.read_text() + f"\n\ndef _added():\n    {line}\n")


@pytest.mark.parametrize(
    "module, line, contract",
    [
        ("codec/checksum.py", "import click", "codec is sans-IO"),
        # One module an envelope (issue 30): they stand apart, and the base knows none of them.
        ("codec/mbap.py", "from mbtool.codec.rtu import crc_verdict", "the framings"),
        ("codec/resync.py", "from mbtool.codec.rtu import RtuFramer", "the framings"),
        ("codec/pdu.py", "from mbtool.errors import ExitCode", "codec is sans-IO"),
        ("link/transport.py", "from mbtool.device.device import Device", "link (the master's I/O)"),
        ("link/scan.py", "from mbtool.cli.sinks import render", "link (the master's I/O)"),
        ("device/server.py", "from mbtool.link.client import Client", "device (the simulated device)"),
        ("monitor/bus.py", "import rich", "monitor (the passive bus monitor)"),
        ("durations.py", "from mbtool.codec.pdu import Request", "durations (the histogram"),
        (
            "cli/commands/scan.py",
            "from mbtool.cli.commands import read",
            "commands do not import one another",
        ),
        # link.client imports link.transport: the reverse, even inside a function, is a cycle.
        ("link/transport.py", "from mbtool.link import client", "no import cycles"),
    ],
)
def test_a_forbidden_import_inside_a_function_breaks_its_contract(copy, module, line, contract):
    _add_to_function(copy / "mbtool" / module, line)
    res = lint(copy)
    assert res.returncode == 1, res.stdout + res.stderr
    broken = res.stdout.split("Broken contracts", 1)[1]
    assert contract in broken


RUFF = [sys.executable, "-m", "ruff"]


def ruff(where: Path, *args: str, paths: tuple[str, ...] = ("mbtool",)) -> subprocess.CompletedProcess:
    return subprocess.run(
        [*RUFF, *args, "--no-cache", *paths], cwd=where, capture_output=True, text=True, timeout=100
    )


def test_ruff_passes_and_formats_nothing():
    for args in (("check",), ("format", "--check")):
        res = ruff(ROOT, *args)
        assert res.returncode == 0, res.stdout + res.stderr


def test_the_tests_benches_and_scripts_are_as_ruff_formats_them():
    res = ruff(ROOT, "format", "--check", paths=("tests", "bench", "scripts"))
    assert res.returncode == 0, res.stdout + res.stderr


def test_an_import_inside_a_function_is_refused(copy):
    # csv costs a one-shot nothing it would not pay at the top: no reason to keep it in a function.
    _add_to_function(copy / "mbtool" / "cli" / "sinks" / "plain.py", "import csv")
    res = ruff(copy, "check")
    assert res.returncode == 1 and "PLC0415" in res.stdout, res.stdout + res.stderr


@pytest.mark.long  # 4 s of CPU, 10 s on a busy machine, and collected last: started first instead
def test_mypy_passes_on_mbtool(tmp_path_factory):
    # Issue 41 point 7: the annotations hold, and the records' constructors are checked
    # (record's dataclass_transform).  The cache is this run's own: a stale one shared
    # between worktrees could hide an error.
    cache = tmp_path_factory.mktemp("mypy_cache")
    res = subprocess.run(
        [sys.executable, "-m", "mypy", "--cache-dir", str(cache), "mbtool"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=100,
    )
    assert res.returncode == 0 and res.stdout.startswith("Success: no issues found"), res.stdout + res.stderr


def test_mypy_reads_a_records_constructor(copy):
    # A record built with a field it does not have, or a value of the wrong type, is refused:
    # without dataclass_transform on @record the checker would see a bare `type` and pass it.
    (copy / "mbtool" / "codec" / "record_use.py").write_text(
        "from mbtool.codec.data_access import ReadHoldingRegisters\n\n"
        "ReadHoldingRegisters(address='0', count=1)\n"
        "ReadHoldingRegisters(address=0, count=1, colour=1)\n"
    )
    res = subprocess.run(
        [sys.executable, "-m", "mypy", "--cache-dir", str(copy / "cache"), "mbtool/codec/record_use.py"],
        cwd=copy,
        capture_output=True,
        text=True,
        timeout=100,
    )
    assert 'record_use.py:3: error: Argument "address"' in res.stdout, res.stdout + res.stderr
    assert 'record_use.py:4: error: Unexpected keyword argument "colour"' in res.stdout, res.stdout


# ARCHITECTURE.md is the map a newcomer reads first (issue 41): every module of mbtool/ is named
# there, by its path (`link/managed.py`, `cli/commands/read.py`), its dotted name
# (`link.managed`), or its file name in the table row of the package it is in (the row of
# `mbtool/link/` naming `managed.py`); a package's `__init__.py` by the package (`mbtool/link/`).
ARCHITECTURE = ROOT / "ARCHITECTURE.md"


def _package_rows(text: str) -> dict[str, str]:
    """The table's rows by the folder in their first cell: {"link/": "| `mbtool/link/` | ..."}."""
    rows = {}
    for line in text.splitlines():
        first = re.match(r"\| `mbtool/([\w/]*?)/?` \|", line)
        if first:
            rows[first.group(1) + "/" if first.group(1) else ""] = line
    return rows


def _names(token: str, relative: str) -> bool:
    """Whether a `token` of the text names the module at ``relative`` (link/managed.py): by its
    path, or by its dotted name or something in it (`link.managed.ManagedLink`)."""
    token = token.removeprefix("mbtool/").removeprefix("mbtool.")
    dotted = relative.removesuffix(".py").replace("/", ".")
    return token == relative or token == dotted or token.startswith(dotted + ".")


def unnamed_modules(mbtool: Path, text: str) -> list[str]:
    rows = _package_rows(text)
    tokens = set(re.findall(r"`([^`]+)`", text))
    missing = []
    for path in sorted(mbtool.rglob("*.py")):
        relative = path.relative_to(mbtool).as_posix()  # link/managed.py
        folder = relative.rpartition("/")[0] + "/" if "/" in relative else ""
        if path.name == "__init__.py":
            if not folder or folder in rows or {folder, f"mbtool/{folder}"} & tokens:
                continue
        elif any(_names(token, relative) for token in tokens):
            continue
        else:
            # The row of the nearest folder above it names it by its path from there.
            parts = relative.split("/")
            cut = len(parts) - 1
            while cut and "".join(part + "/" for part in parts[:cut]) not in rows:
                cut -= 1
            row = rows.get("".join(part + "/" for part in parts[:cut]), "")
            if re.search(rf"`{re.escape('/'.join(parts[cut:]))}[`:]", row):
                continue
        missing.append(relative)
    return missing


def stale_names(root: Path, text: str) -> list[str]:
    """The files ARCHITECTURE.md names (`x.py`, `link/x.py`) that are not there: from the
    repository, from mbtool/, or in a row, from the row's package."""
    folders = {row: f"mbtool/{folder}" for folder, row in _package_rows(text).items()}
    stale = []
    for line in text.splitlines():
        row = folders.get(line)
        for name in re.findall(r"`([\w/]+\.py)`", line):
            places = [root / name, root / "mbtool" / name]
            if row is not None:
                places.append(root / row / name)
            if not any(place.is_file() for place in places):
                stale.append(name)
    return stale


def test_architecture_names_every_module_and_no_other():
    text = ARCHITECTURE.read_text()
    missing = unnamed_modules(ROOT / "mbtool", text)
    assert not missing, f"ARCHITECTURE.md names no {', '.join(missing)}"
    stale = stale_names(ROOT, text)
    assert not stale, f"ARCHITECTURE.md names {', '.join(stale)}, which mbtool has no more"


def test_a_module_left_out_of_architecture_is_caught(tmp_path):
    shutil.copytree(ROOT / "mbtool", tmp_path / "mbtool", ignore=shutil.ignore_patterns("__pycache__"))
    (tmp_path / "mbtool" / "link" / "newcomer.py").write_text('"""A module no one wrote down."""\n')
    (tmp_path / "mbtool" / "fresh").mkdir()
    (tmp_path / "mbtool" / "fresh" / "__init__.py").write_text("")
    missing = unnamed_modules(tmp_path / "mbtool", ARCHITECTURE.read_text())
    assert missing == ["fresh/__init__.py", "link/newcomer.py"]


def test_a_module_gone_but_still_named_is_caught(tmp_path):
    shutil.copytree(ROOT / "mbtool", tmp_path / "mbtool", ignore=shutil.ignore_patterns("__pycache__"))
    for name in ("scripts", "tests"):
        (tmp_path / name).symlink_to(ROOT / name)
    (tmp_path / "mbtool" / "link" / "managed.py").unlink()  # named in link's row, as `managed.py`
    (tmp_path / "mbtool" / "device" / "handlers.py").unlink()  # and by its path, `device/handlers.py`
    stale = stale_names(tmp_path, ARCHITECTURE.read_text())
    assert "managed.py" in stale and "device/handlers.py" in stale
    assert all(name.endswith(("managed.py", "handlers.py")) for name in stale), stale  # those alone
