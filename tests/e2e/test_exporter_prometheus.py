"""Prometheus itself scrapes mbtool exporter (issue 32): Debian's `prometheus` server (.ci/run
installs it) runs on loopback with a configuration made here, scraping every second an
exporter in inventory mode (a static target) and one in multi-target mode (the relabelling
Prometheus documents for exporters of that kind), and the test reads back what it stored
through Prometheus's own HTTP query API: a point's value, modbus_up and a histogram's count;
a device slower than the scrape's timeout, and a target the exporter refuses.

Prometheus's parser is the real judge of the exposition: a sample it could not read would
fail the scrape (up 0), and the values would never appear.
"""

from __future__ import annotations

import contextlib
import json
import shutil
import subprocess
import time
from pathlib import Path
from urllib.parse import urlencode

import pytest
from helpers.devices import start_device
from helpers.exporter import METER_DATA, METER_MAP, exporting, http_get
from helpers.served import serve
from helpers.sockets import free_port

pytestmark = [
    pytest.mark.timeout(180),
    pytest.mark.skipif(
        shutil.which("prometheus") is None, reason="prometheus is not installed (.ci/run installs it)"
    ),
]

READY = 60.0  # seconds for Prometheus to start, and for a value to be scraped and stored


@contextlib.contextmanager
def prometheus(config: str, tmp_path: Path):
    """The prometheus binary on a free loopback port with ``config``; yields its base URL once
    /-/ready says so."""
    (tmp_path / "prometheus.yml").write_text(config)
    port = free_port()
    log = open(tmp_path / "prometheus.log", "w")
    proc = subprocess.Popen(
        [
            "prometheus",
            f"--config.file={tmp_path / 'prometheus.yml'}",
            f"--storage.tsdb.path={tmp_path / 'tsdb'}",
            f"--web.listen-address=127.0.0.1:{port}",
            "--log.level=warn",
        ],
        stdout=log,
        stderr=subprocess.STDOUT,
        stdin=subprocess.DEVNULL,
    )
    url = f"http://127.0.0.1:{port}"
    try:
        end = time.monotonic() + READY
        while True:
            try:
                if http_get(url + "/-/ready", timeout=2)[0] == 200:
                    break
            except OSError:
                pass
            if proc.poll() is not None or time.monotonic() > end:
                pytest.fail(
                    f"prometheus did not get ready:\n{(tmp_path / 'prometheus.log').read_text()[-3000:]}"
                )
            time.sleep(0.2)
        yield url
    finally:
        proc.terminate()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)
        log.close()


def query(prom: str, expression: str) -> list[dict]:
    """The instant vector an expression gives now, through /api/v1/query."""
    status, _, body = http_get(f"{prom}/api/v1/query?{urlencode({'query': expression})}", timeout=10)
    reply = json.loads(body)
    assert status == 200 and reply["status"] == "success", body
    return reply["data"]["result"]


def stored(prom: str, expression: str, tmp_path: Path) -> float:
    """The one value an expression gives, once Prometheus has scraped and stored it."""
    end = time.monotonic() + READY
    while time.monotonic() < end:
        result = query(prom, expression)
        if len(result) == 1:
            return float(result[0]["value"][1])
        time.sleep(0.5)
    targets = http_get(f"{prom}/api/v1/targets", timeout=10)[2]
    pytest.fail(f"no value for {expression} after {READY} s; targets: {targets}")


def test_prometheus_scrapes_the_exporter_in_both_modes(tmp_path, refused_port, silent_server):
    plant_dir = tmp_path / "plant"
    plant_dir.mkdir()
    shutil.copy(METER_MAP, plant_dir / "meter.toml")
    maps = tmp_path / "maps"
    maps.mkdir()
    shutil.copy(METER_MAP, maps / "energy-meter.toml")
    with (
        serve("--data", str(METER_DATA)) as meter,
        serve("--delay", "3", "--data", str(METER_DATA)) as slow,
        start_device(tcp=True, framer="socket", units="1") as pymodbus_device,
    ):
        (plant_dir / "plant.toml").write_text(f"""
[poll]
interval = 0.5
offline_after = 1

[links.gw]
target = "{meter.target}"
timeout = 0.5

[links.plc]
target = "{pymodbus_device.target}"

[devices.meter1]
link = "gw"
map = "meter.toml"
tags = {{ site = "north" }}

[devices.dead]
link = "gw"
unit = 9
read = ["40001 1"]

[devices.plc]
link = "plc"
read = ["40001 2"]
""")
        with (
            exporting(plant_dir / "plant.toml", tmp_path=tmp_path) as inventory,
            exporting("--maps", maps, "--allow-target", "tcp://127.0.0.1:*", tmp_path=tmp_path) as multi,
        ):
            refused = silent_server.socket_target  # no pattern allows socket://
            config = f"""
global:
  scrape_interval: 1s
  scrape_timeout: 1s
scrape_configs:
  - job_name: plant
    static_configs:
      - targets: ["{inventory.url.removeprefix("http://")}"]
  - job_name: modbus
    metrics_path: /modbus
    params:
      module: [energy-meter]
    static_configs:
      - targets: ["{meter.target}", "{slow.target}", "{refused}", "tcp://127.0.0.1:{refused_port}"]
    relabel_configs:
      - source_labels: [__address__]
        target_label: __param_target
      - source_labels: [__param_target]
        target_label: instance
      - target_label: __address__
        replacement: {multi.url.removeprefix("http://")}
"""
            with prometheus(config, tmp_path) as prom:
                # Inventory mode: every device from memory.
                assert (
                    stored(prom, 'modbus_voltage_l1{job="plant",device="meter1",site="north"}', tmp_path)
                    == 230.1
                )
                assert stored(prom, 'modbus_up{job="plant",device="meter1"}', tmp_path) == 1
                assert (
                    stored(
                        prom, 'modbus_value{job="plant",device="plc",table="holding",address="0"}', tmp_path
                    )
                    == 100
                )
                assert stored(prom, 'modbus_up{job="plant",device="dead"}', tmp_path) == 0
                assert (
                    stored(
                        prom,
                        'modbus_request_duration_seconds_count{job="plant",device="meter1"} > 0',
                        tmp_path,
                    )
                    > 0
                )
                assert (
                    stored(
                        prom,
                        'modbus_request_duration_seconds_bucket{job="plant",device="plc",le="+Inf"} > 0',
                        tmp_path,
                    )
                    > 0
                )
                assert stored(prom, 'process_resident_memory_bytes{job="plant"}', tmp_path) > 0

                # Multi-target: a map read from each target on each scrape.
                assert (
                    stored(prom, f'modbus_voltage_l1{{job="modbus",instance="{meter.target}"}}', tmp_path)
                    == 230.1
                )
                assert stored(prom, f'modbus_up{{job="modbus",instance="{meter.target}"}}', tmp_path) == 1
                # A device slower than the scrape's timeout: answered within it, modbus_up 0 and
                # why, and the scrape itself succeeded (up 1).
                assert stored(prom, f'modbus_up{{job="modbus",instance="{slow.target}"}}', tmp_path) == 0
                assert stored(prom, f'up{{job="modbus",instance="{slow.target}"}}', tmp_path) == 1
                assert (
                    stored(prom, f'modbus_error_info{{instance="{slow.target}",kind="timeout"}}', tmp_path)
                    == 1
                )
                assert stored(prom, f'scrape_duration_seconds{{instance="{slow.target}"}}', tmp_path) < 1
                # A target that does not answer: modbus_up 0 with the reason, not a failed scrape.
                dead = f"tcp://127.0.0.1:{refused_port}"
                assert (
                    stored(prom, f'modbus_error_info{{instance="{dead}",kind="connection"}}', tmp_path) == 1
                )
                assert stored(prom, f'up{{instance="{dead}"}}', tmp_path) == 1
                # A target the exporter refuses (403): the scrape fails, and nothing was opened.
                assert stored(prom, f'up{{job="modbus",instance="{refused}"}}', tmp_path) == 0
                assert query(prom, f'modbus_up{{instance="{refused}"}}') == []
                targets = json.loads(http_get(f"{prom}/api/v1/targets", timeout=10)[2])["data"][
                    "activeTargets"
                ]
                (target,) = [t for t in targets if t["labels"]["instance"] == refused]
                assert "403" in target["lastError"], target
    assert silent_server.connections == 0
