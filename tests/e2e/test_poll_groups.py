"""Poll groups on the wire (issue 44): mbtool poll of a device behind ``mbtool serve``, whose
every reply takes 0.2 s, with a fast group of one read every 0.6 s and a slow group of eight
reads (1.6 s of replies) every 4 s: the fast group keeps its pace while the slow group is read, held up by
one transaction at most, never by the slow group's whole poll."""

from __future__ import annotations

import json
import re
import statistics
from datetime import datetime

import pytest
from helpers.checks import expect_ok
from helpers.run import run_mbtool
from helpers.served import serve

pytestmark = [pytest.mark.e2e, pytest.mark.timeout(60)]

REPLY = 0.2  # serve --delay: each transaction's time
FAST = 0.6


def test_a_fast_group_keeps_its_pace_while_a_slow_groups_long_poll_is_read(tmp_path):
    # eight points two registers apart: eight reads (max_gap 0), one for the fast group
    points = "".join(f"[points.p{n}]\nref = {40011 + 2 * n}\n" for n in range(8))
    (tmp_path / "m.toml").write_text("[points.power]\nref = 40001\n" + points)
    slow = ", ".join(f'"p{n}"' for n in range(8))
    with serve("--delay", str(REPLY)) as device:
        plant = tmp_path / "plant.toml"
        plant.write_text(
            f'[poll]\ninterval = 60\n[links.gw]\ntarget = "{device.target}"\ntimeout = 1\n'
            '[devices.m]\nlink = "gw"\nmap = "m.toml"\n'
            f'[devices.m.groups.fast]\ninterval = {FAST}\npoints = ["power"]\n'
            f"[devices.m.groups.slow]\ninterval = 4\npoints = [{slow}]\n"
        )
        result = expect_ok(run_mbtool("poll", plant, "-o", "json", "--duration", "6", "--stats", "json"))
    records = [json.loads(line) for line in result.stdout.splitlines()]
    assert all("group" in r for r in records), records  # no event: the link keeps up (3.7 reads/s of 5)
    fast = [r for r in records if r["group"] == "fast"]
    slow_polls = [r for r in records if r["group"] == "slow"]
    assert all([p["name"] for p in r["points"]] == ["power"] for r in fast)
    assert all(len(r["points"]) == 8 for r in slow_polls) and len(slow_polls) >= 2
    stamps = [_seconds(r["time"]) for r in fast]
    gaps = [b - a for a, b in zip(stamps, stamps[1:], strict=False)]
    # a whole slow poll (1.6 s) in the way would make a gap of 2 s; one transaction, 0.8 s at most
    assert max(gaps) < FAST + REPLY + 0.15, gaps
    assert abs(statistics.mean(gaps) - FAST) < 0.05, gaps
    stats = json.loads(result.stderr.splitlines()[0])["devices"]["m"]["groups"]
    assert stats["fast"]["interval_seconds"] == FAST and stats["fast"]["polls"] == len(fast)
    assert abs(stats["fast"]["achieved_seconds"] - FAST) < 0.05


def _seconds(stamp: str) -> float:
    return datetime.fromisoformat(stamp).timestamp()


def test_a_link_that_cannot_keep_up_says_so_once_in_the_runs_log_format(tmp_path):
    """Two reads every 0.1 s of a device that takes 0.1 s a reply: 20 reads a second asked, some
    10 carried.  One warning, with the figures, through poll's log lines (--log-format)."""
    (tmp_path / "m.toml").write_text("[points.a]\nref = 40001\n[points.b]\nref = 40011\n")
    with serve("--delay", "0.1") as device:
        plant = tmp_path / "plant.toml"
        plant.write_text(
            f'[poll]\ninterval = 5\n[links.gw]\ntarget = "{device.target}"\ntimeout = 1\n'
            '[devices.m]\nlink = "gw"\nmap = "m.toml"\n'
            '[devices.m.groups.fast]\ninterval = 0.1\npoints = ["a", "b"]\n'
        )
        result = expect_ok(
            run_mbtool("poll", plant, "-o", "json", "--duration", "3", "--log-format", "logfmt")
        )
    said = [line for line in result.stderr.splitlines() if "reads/s" in line]
    assert len(said) == 1, result.stderr
    assert "level=warning" in said[0] and "link=gw" in said[0], said
    figures = re.search(r"asked ([\d.]+) reads/s, the line carries ([\d.]+)", said[0])
    assert figures and float(figures[1]) == 20.0 and 7 < float(figures[2]) < 10.5, said
