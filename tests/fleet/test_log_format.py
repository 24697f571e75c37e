"""--log-format telegraf|logfmt|json (issue 44): mbtool's stderr lines (events, warnings,
errors) with a level, so Telegraf's execd logs a device offline as a warning and its return as
information, not every change of state as an error; logfmt and json one record a line."""

from __future__ import annotations

import json
import re

import pytest
from helpers.run import run_cli

from mbtool.cli.plant_text import event_log
from mbtool.plant.schedule import Event

# A plant of a device that answers (sim://) and one on a link nothing listens on, tried once.
PLANT = """\
[poll]
offline_after = 1
[links.good]
target = "sim://"
[links.dead]
target = "tcp://127.0.0.1:{port}"
timeout = 0.2
retries = 0
[devices.meter1]
link = "good"
read = ["40001"]
[devices.gone]
link = "dead"
read = ["40001"]
"""

LOGFMT_PAIR = re.compile(r'([a-z_]+)=("(?:[^"\\]|\\.)*"|[^ "=]+)(?: |$)')


@pytest.fixture
def plant(tmp_path, silent_server):
    path = tmp_path / "plant.toml"
    path.write_text(PLANT.format(port=silent_server.port))
    return path


def logfmt(line: str) -> dict[str, str]:
    """A logfmt line's pairs, the whole line consumed by them (else it is no logfmt)."""
    pairs = LOGFMT_PAIR.findall(line)
    assert "".join(f"{k}={v} " for k, v in pairs).rstrip() == line, line
    return {key: json.loads(value) if value.startswith('"') else value for key, value in pairs}


def test_telegraf_prefixes_each_line_with_its_level(plant):
    res = run_cli("poll", plant, "--once", "--log-format", "telegraf")
    assert res.returncode == 8, res
    lines = res.stderr.splitlines()
    assert lines and all(line[:3] in ("E! ", "W! ", "I! ") for line in lines), res
    offline = [line for line in lines if " gone offline" in line]
    assert offline and all(line.startswith("W! ") for line in offline), res
    assert lines[-1].startswith("W! ") and "1 of 2 devices answered" in lines[-1]  # partial: exit 8


def test_logfmt_is_one_record_a_line(plant):
    res = run_cli("poll", plant, "--once", "--log-format", "logfmt")
    records = [logfmt(line) for line in res.stderr.splitlines()]
    assert all(r["level"] in ("error", "warning", "info") and "msg" in r and "time" in r for r in records)
    event = next(r for r in records if r.get("device") == "gone")
    assert event["level"] == "warning" and event["state"] == "offline" and event["reason"]


def test_json_is_one_object_a_line(plant):
    res = run_cli("poll", plant, "--once", "--log-format", "json")
    records = [json.loads(line) for line in res.stderr.splitlines()]
    assert all(set(r) >= {"time", "level", "msg"} for r in records), res
    assert any(r.get("device") == "gone" and r["level"] == "warning" for r in records)


def test_a_usage_error_is_an_error(tmp_path):
    path = tmp_path / "plant.toml"
    path.write_text("[poll]\ncolour = 1\n")
    res = run_cli("poll", path, "--log-format", "telegraf")
    assert res.returncode == 2 and res.stderr.startswith("E! mbtool: ") and res.stderr.count("\n") == 1, res
    res = run_cli("poll", path, env={"MBTOOL_LOG_FORMAT": "json"})
    assert res.returncode == 2 and json.loads(res.stderr)["level"] == "error", res


@pytest.mark.parametrize("state, level, prefix", [("offline", "warning", "W! "), ("online", "info", "I! ")])
def test_a_device_offline_is_a_warning_and_back_online_information(state, level, prefix):
    event = Event(1.5e9, "device", "meter1", state, "no response" if state == "offline" else "")
    assert event_log(event, "telegraf").startswith(prefix + "mbtool: ")
    assert f"meter1 {state}" in event_log(event, "telegraf")
    record = json.loads(event_log(event, "json"))
    assert record["device"] == "meter1" and record["state"] == state and record["level"] == level


def test_the_text_format_is_as_before(plant):
    """The events and the last line as they were: mbtool: and the line (the statistics a table)."""
    res = run_cli("poll", plant, "--once")
    lines = res.stderr.splitlines()
    assert [ln for ln in lines if " gone offline" in ln][0].startswith("mbtool: ") and lines[-1].startswith(
        "mbtool: "
    )
