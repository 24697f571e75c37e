"""Renderers: golden output at a fixed width with no colour; rich only for tables."""

from __future__ import annotations

import io
import json
import subprocess
import sys

from mbtool.cli.sinks.json import to_json
from mbtool.cli.sinks import render
from mbtool.cli.results import Result, as_dict

REGISTERS = Result(
    1,
    3,
    "Read Holding Registers",
    100,
    [21.5, float("nan")],
    "float32",
    [0x41AC, 0, 0x7FC0, 0],
    addresses=[100, 102],
)
BITS = Result(17, 1, "Read Coils", 19, [True, False])


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
    text = rendered(Result(1, 3, "Read Holding Registers", 0, [7], "uint16", [7]), "table")
    assert text == (
        "Read Holding Registers · FC 03 (0x03) · unit 1\n"
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


def _on_a_terminal(env_extra: dict[str, str]) -> str:
    """Run mbtool with stdout on a pseudo-terminal, as a user at a shell would."""
    import os

    main_fd, tty_fd = os.openpty()
    env = {k: v for k, v in os.environ.items() if k not in ("NO_COLOR", "FORCE_COLOR")}
    env.update({"TERM": "xterm-256color", "COLUMNS": "80", **env_extra})
    proc = subprocess.run(
        [sys.executable, "-m", "mbtool", "read-coils", "0", "2", "-p", "sim://"],
        stdout=tty_fd,
        stderr=subprocess.PIPE,
        env=env,
        timeout=30,
    )
    os.close(tty_fd)
    chunks = []
    while True:
        try:
            chunk = os.read(main_fd, 4096)
        except OSError:  # EIO: the terminal's other end is closed and drained
            break
        if not chunk:
            break
        chunks.append(chunk)
    os.close(main_fd)
    assert proc.returncode == 0, proc.stderr
    return b"".join(chunks).decode()


def test_a_terminal_gets_a_coloured_table_unless_no_color():
    coloured = _on_a_terminal({})
    assert "┏━━━━━━━━━┳━━━━━━━┓" in coloured  # the default on a terminal is the table
    assert "\x1b[32m" in coloured  # ON in green
    plain = _on_a_terminal({"NO_COLOR": "1"})
    assert "┏━━━━━━━━━┳━━━━━━━┓" in plain
    assert "\x1b[32m" not in plain
