"""Renderers: golden output at a fixed width with no colour; rich only for tables."""

from __future__ import annotations

import io
import json
import subprocess
import sys

from mbtool.render import Result, as_dict, render, to_json

REGISTERS = Result(
    1, 3, "Read Holding Registers", 100, [(100, 21.5), (102, float("nan"))], "float32", [0x41AC, 0, 0x7FC0, 0]
)
BITS = Result(17, 1, "Read Coils", 19, [(19, True), (20, False)])


def rendered(result: Result, fmt: str) -> str:
    out = io.StringIO()
    render(result, fmt, out)
    return out.getvalue()


def test_plain_is_address_value_lines():
    assert rendered(BITS, "plain") == "19 1\n20 0\n"
    assert rendered(REGISTERS, "plain") == "100 21.5\n102 nan\n"


def test_json_has_the_contract_keys_and_no_nan():
    data = json.loads(rendered(REGISTERS, "json"))
    assert data == {
        "unit": 1,
        "function": 3,
        "name": "Read Holding Registers",
        "address": 100,
        "type": "float32",
        "values": [21.5, None],
        "addresses": [100, 102],
        "registers": [0x41AC, 0, 0x7FC0, 0],
    }
    assert as_dict(BITS)["values"] == [True, False]


def test_to_json_agrees_with_the_json_module():
    data = {"a": [1, -2.5, 1e300, True, False, None], "s": 'quote " back\\ nl\n é \x00', "t": (1, 2), "n": {}}
    assert json.loads(to_json(data)) == json.loads(json.dumps(data))
    assert to_json(float("inf")) == "null"


def test_csv_has_a_header():
    assert rendered(BITS, "csv") == "address,value\n19,1\n20,0\n"


def test_table_golden(monkeypatch):
    monkeypatch.setenv("COLUMNS", "60")
    monkeypatch.setenv("NO_COLOR", "1")
    text = rendered(Result(1, 3, "Read Holding Registers", 0, [(0, 7)], "uint16", [7]), "table")
    assert text == (
        "Read Holding Registers (FC 03) · unit 1\n"
        "┏━━━━━━━━━┳━━━━━━━┳━━━━━━━━┓\n"
        "┃ Address ┃ Value ┃    Hex ┃\n"
        "┡━━━━━━━━━╇━━━━━━━╇━━━━━━━━┩\n"
        "│       0 │     7 │ 0x0007 │\n"
        "└─────────┴───────┴────────┘\n"
    )


def test_typed_table_shows_the_registers_behind_each_value(monkeypatch):
    monkeypatch.setenv("COLUMNS", "60")
    text = rendered(REGISTERS, "table")
    assert "│     100 │  21.5 │ 41AC 0000 │" in text
    assert "│     102 │   nan │ 7FC0 0000 │" in text


def test_rich_is_imported_only_for_tables():
    code = (
        "import sys; from mbtool.cli import main; sys.argv = ['mbtool', 'read-holding-registers', '0', '3',"
        " '-p', 'sim://', '-o', 'json'];\n"
        "import atexit; atexit.register(lambda: print('RICH' if 'rich' in sys.modules else 'NO RICH', file=sys.stderr))\n"
        "main()"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=30)
    assert result.returncode == 0, result.stderr
    assert "NO RICH" in result.stderr
