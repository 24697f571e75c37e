"""A fleet's labels (issue 44): [poll] site and instance (instance: the host name unless given)
on every record of every output, so two pollers' data never collide where they meet."""

from __future__ import annotations

import socket

import pytest
from helpers.checks import assert_one_error_line, expect_ok, json_lines, wait_until
from helpers.exporter import exporting
from helpers.prometheus import promtool_check
from helpers.run import run_cli
from prometheus_client.parser import text_string_to_metric_families

PLANT = """\
[poll]
{poll}
[links.bus1]
target = "sim://"
[devices.meter1]
link = "bus1"
read = ["40001 2"]
tags = {{ room = "b2" }}
"""


def plant(tmp_path, poll: str = 'site = "north"\ninstance = "poller-a"'):
    path = tmp_path / "plant.toml"
    path.write_text(PLANT.format(poll=poll))
    return path


def test_json_records_carry_site_and_instance(tmp_path):
    records = json_lines(expect_ok(run_cli("poll", plant(tmp_path), "--once", "-o", "json")).stdout)
    polls = [r for r in records if "device" in r]
    assert polls and all(r["site"] == "north" and r["instance"] == "poller-a" for r in polls)
    assert polls[0]["tags"] == {"room": "b2"}


def test_influx_lines_are_tagged_with_site_and_instance(tmp_path):
    line = expect_ok(run_cli("poll", plant(tmp_path), "--once", "-o", "influx")).stdout.strip()
    tags = line.split(" ", 1)[0].split(",")[1:]
    assert {"site=north", "instance=poller-a", "room=b2", "device=meter1"} <= set(tags)


def test_prometheus_samples_are_labelled_with_site_and_instance(tmp_path):
    text = expect_ok(run_cli("poll", plant(tmp_path), "--once", "-o", "prom")).stdout
    promtool_check(text)
    samples = [s for family in text_string_to_metric_families(text) for s in family.samples]
    assert samples
    for sample in samples:
        assert sample.labels["site"] == "north" and sample.labels["instance"] == "poller-a", sample


def test_the_instance_is_the_host_name_unless_given(tmp_path):
    out = expect_ok(run_cli("poll", plant(tmp_path, 'site = "north"'), "--once", "-o", "json")).stdout
    assert json_lines(out)[0]["instance"] == socket.gethostname()


def test_without_labels_the_records_are_as_before_but_the_instance(tmp_path):
    record = json_lines(expect_ok(run_cli("poll", plant(tmp_path, ""), "--once", "-o", "json")).stdout)[0]
    assert "site" not in record and record["instance"] == socket.gethostname()


@pytest.mark.parametrize(
    "poll, words",
    [
        ("site = 3", "[poll] site: expected"),
        ('site = ""', "[poll] site: expected"),
        ('instance = "a\\nb"', "[poll] instance: expected"),
    ],
    ids=["number", "empty", "two-lines"],
)
def test_a_bad_label_is_exit_2_naming_the_key(tmp_path, poll, words):
    path = plant(tmp_path, poll)
    line = assert_one_error_line(run_cli("poll", path, "--once"), 2)
    assert str(path) in line and words in line


def test_a_device_tag_may_not_be_named_as_a_fleet_label(tmp_path):
    path = tmp_path / "plant.toml"
    path.write_text(PLANT.format(poll='site = "north"').replace('room = "b2"', 'instance = "x"'))
    line = assert_one_error_line(run_cli("poll", path, "--once"), 2)
    assert "[devices.meter1] tags: 'instance'" in line


def test_every_sample_of_the_exporters_metrics_is_labelled(tmp_path):
    """The exporter's /metrics: the devices' values and the devices' and links' statistics
    (prometheus_client's process_ and python_ families are the process's, not the plant's)."""

    with exporting(str(plant(tmp_path)), tmp_path=tmp_path) as running:
        assert wait_until(lambda: "modbus_polls_total" in running.get("/metrics")[2], 10)
        text = running.get("/metrics")[2]
    promtool_check(text)
    families = list(text_string_to_metric_families(text))
    assert {"modbus_link_up", "modbus_polls", "modbus_up"} <= {f.name for f in families}
    for family in (f for f in families if f.name.startswith("modbus_")):
        for sample in family.samples:
            assert sample.labels["site"] == "north" and sample.labels["instance"] == "poller-a", sample
