"""poll's live view on real terminals of the sizes field engineers have (issue 39.6): tmux at
100x30 and 80x24, its screen read back with capture-pane.

A plant of more devices than the screen has rows, each with more values than a row holds,
and a link that cannot be opened: the changes of state (the only place that says why a link
is offline) stay on the screen in a band of their own, the table is cut first and says how
many devices it left out, and a device's values are cut at the end of its row.
"""

from __future__ import annotations

import os
import shlex
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest
from helpers.run import REPO_ROOT, mbtool_env
from helpers.sockets import free_port

pytestmark = pytest.mark.skipif(shutil.which("tmux") is None, reason="tmux is not installed")

DEVICES = 30  # on sim://, each with 12 values: more rows, and more values, than a screen holds


def _plant(path: Path, refused: int) -> Path:
    # Every 5 s: the screens are taken after the first round, and a first round that a loaded
    # machine makes slow is no overrun (late by a tenth of its interval), whose notice would take the
    # events' band from the link's event the tests look for.
    text = f"""
[poll]
interval = 5

[links.bus1]
target = "sim://"

[links.cabinet]
target = "tcp://127.0.0.1:{refused}"
timeout = 0.3
"""
    for n in range(1, DEVICES + 1):
        text += f'\n[devices.meter{n}]\nlink = "bus1"\nunit = 1\nread = ["40001 8", "00001 4"]\n'
    text += '\n[devices.pump]\nlink = "cabinet"\nunit = 1\nread = ["40001 2"]\n'
    path.write_text(text)
    return path


def _screen(plant: Path, columns: int, rows: int, until, wait: float = 15.0) -> list[str]:
    """``mbtool poll PLANT`` in a tmux window of that size: its screen once ``until(lines)``
    holds (or at the deadline), as capture-pane shows it."""
    server = f"mbtool-test-{os.getpid()}-{columns}x{rows}"
    tmux = ["tmux", "-L", server, "-f", "/dev/null"]
    env = mbtool_env()
    for sized in ("COLUMNS", "LINES"):  # rich reads the terminal's size, as on a real one
        env.pop(sized, None)
    command = shlex.join([sys.executable, "-m", "mbtool", "poll", str(plant)]) + " 2>/dev/null"
    subprocess.run(
        [*tmux, "new-session", "-d", "-x", str(columns), "-y", str(rows), "-c", str(REPO_ROOT), command],
        env=env,
        check=True,
        timeout=10,
    )
    try:
        end = time.monotonic() + wait
        while True:
            shown = subprocess.run(
                [*tmux, "capture-pane", "-p"], capture_output=True, text=True, timeout=10, check=True
            ).stdout.splitlines()
            if until(shown) or time.monotonic() > end:
                return shown
            time.sleep(0.2)
    finally:
        subprocess.run([*tmux, "kill-server"], timeout=10, check=False)


@pytest.mark.parametrize(("columns", "rows"), [(100, 30), (80, 24)])
def test_the_live_view_fits_the_terminal_the_events_first_then_the_table_cut(tmp_path, columns, rows):
    plant = _plant(tmp_path / "plant.toml", free_port())

    def settled(lines):  # every device polled, and the link's event out
        text = "\n".join(lines)
        return "link cabinet offline: " in text and "more devices" in text and "40001=" in text

    shown = _screen(plant, columns, rows, settled)
    text = "\n".join(shown)
    assert len(shown) <= rows and all(len(line) <= columns for line in shown), text

    # The event that says why the link is offline is on the screen, whole.
    event = [n for n, line in enumerate(shown) if "link cabinet offline: " in line]
    assert event, text
    said = " ".join(shown[event[0] : event[0] + 3])
    assert "connection refused" in said.lower() and "next try in" in said, text

    # The table was cut, not the events: a line says how many devices are not shown, and the
    # rows shown and the ones it counts make the whole plant.
    more = [line for line in shown if "more devices" in line]
    assert len(more) == 1, text
    hidden = int(more[0].split("+")[1].split()[0])
    rows_shown = [
        line for line in shown if line.split()[:1] and line.split()[0].startswith(("meter", "pump"))
    ]
    assert hidden >= 1 and len(rows_shown) + hidden == DEVICES + 1, text

    # A device's values stay on its row, cut at its end: no row of values alone.
    valued = [line for line in shown if "40001=" in line]
    assert valued, text
    for line in valued:
        assert line.split()[0].startswith("meter"), f"a row of values alone:\n{text}"
        assert line.rstrip().endswith("…"), f"twelve values are not cut at the row's end:\n{text}"
    assert text.count("40002=") == len(valued), text  # one row a device, not a row a point
