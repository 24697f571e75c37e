"""A plant's Prometheus text (cli/plant_text.py) is kept as families, data, until it is
written: never written and cut apart again (issue 41: ``split_families`` re-parsed the text the
code itself had just written, and the exporter found its own metric names by a regex on it)."""

from __future__ import annotations

from prometheus_client.parser import text_string_to_metric_families

from mbtool.cli import plant_text
from mbtool.cli.plant_text import PlantMetrics, device_stats, link_stats
from mbtool.cli.sinks.prom import written
from mbtool.link.stats import Stats
from mbtool.plant.schedule import LinkView
from mbtool.plant.stats import PollStats


def test_a_devices_and_a_links_statistics_are_families_written_once():
    assert not hasattr(plant_text, "split_families")
    device = device_stats("meter1", PollStats(), {"site": "north"})
    link = link_stats("bus1", Stats(), True, 2)
    names = [name for name, _, _ in device + link]
    assert names[:2] == ["modbus_polls_total", "modbus_failed_polls_total"]
    assert "modbus_request_duration_seconds" in names and "modbus_link_up" in names
    assert len(names) == len(set(names))
    parsed = {f.name: f for f in text_string_to_metric_families(written(device + link))}  # the real parser
    assert parsed["modbus_link_up"].samples[0].value == 1
    assert parsed["modbus_link_open_failures"].samples[0].value == 2
    assert parsed["modbus_polls"].samples[0].labels == {"device": "meter1", "site": "north"}


def test_the_exporter_keeps_each_report_as_its_families():
    metrics = PlantMetrics()
    metrics._link(LinkView("bus1", "online", 0, Stats()))
    assert metrics.blocks[("link", "bus1")] == link_stats("bus1", Stats(), True, 0)
