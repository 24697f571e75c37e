"""Two shards' exporters, each scraped by a Prometheus in agent mode that remote-writes to a
central Prometheus (Debian's, --web.enable-remote-write-receiver): the central server's HTTP
API holds both shards' series, each with its site and instance labels (issue 44)."""

from __future__ import annotations

import json
import shutil
import subprocess
import urllib.parse
import urllib.request

import pytest
from helpers.checks import wait_until
from helpers.exporter import exporting
from helpers.run import mbtool_env
from helpers.sockets import free_port

from mbtool.plant.inventory import shard_of

pytestmark = [pytest.mark.e2e, pytest.mark.skipif(shutil.which("prometheus") is None, reason="no prometheus")]

LINKS = [f"bus{i}" for i in range(8)]


def prometheus(tmp_path, name: str, config: str, *flags: str) -> tuple[subprocess.Popen, int]:
    port = free_port()
    (tmp_path / f"{name}.yml").write_text(config)
    proc = subprocess.Popen(
        ["prometheus", f"--config.file={tmp_path / f'{name}.yml'}", f"--web.listen-address=127.0.0.1:{port}", *flags],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=mbtool_env(),
    )  # fmt: skip
    return proc, port


def query(port: int, expr: str) -> list:
    url = f"http://127.0.0.1:{port}/api/v1/query?" + urllib.parse.urlencode({"query": expr})
    try:
        with urllib.request.urlopen(url, timeout=2) as response:
            return json.load(response)["data"]["result"]
    except OSError:
        return []


def test_two_agents_remote_write_both_shards_to_a_central_server(tmp_path):
    inventory = "".join(
        f'[links.{n}]\ntarget = "sim://"\n[devices.m{n}]\nlink = "{n}"\nread = ["40001"]\n' for n in LINKS
    )
    procs = []
    central, central_port = prometheus(
        tmp_path,
        "central",
        "global: {}\n",
        "--web.enable-remote-write-receiver",
        f"--storage.tsdb.path={tmp_path / 'c'}",
    )
    procs.append(central)
    try:
        with (
            exporting(_plant(tmp_path, 0, inventory), "--shard", "0/2", tmp_path=tmp_path) as e0,
            exporting(_plant(tmp_path, 1, inventory), "--shard", "1/2", tmp_path=tmp_path) as e1,
        ):
            for k, exporter in enumerate((e0, e1)):
                target = exporter.url.split("//", 1)[1].rstrip("/")
                agent, _ = prometheus(
                    tmp_path, f"agent{k}",
                    "global: {scrape_interval: 1s}\nscrape_configs:\n  - job_name: mbtool\n    honor_labels: true\n"
                    f"    static_configs: [{{targets: ['{target}']}}]\n"
                    f"remote_write:\n  - url: http://127.0.0.1:{central_port}/api/v1/write\n"
                    # sent within 0.2 s of the scrape, not the 5 s a batch may wait by default
                    "    queue_config: {batch_send_deadline: 200ms}\n",
                    "--enable-feature=agent", f"--storage.agent.path={tmp_path / f'a{k}'}",
                )  # fmt: skip
                procs.append(agent)
            series: list = []

            def arrived() -> bool:
                series[:] = query(central_port, "modbus_up")
                return len(series) == len(LINKS)

            assert wait_until(arrived, 45, 0.5), series
    finally:
        for proc in reversed(procs):  # the agents first: they flush to the central server
            proc.terminate()
        for proc in reversed(procs):
            try:
                proc.wait(3)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(5)
    by_device = {s["metric"]["device"]: s["metric"] for s in series}
    for name in LINKS:
        labels = by_device[f"m{name}"]
        k = shard_of(name, 2)
        assert labels["site"] == "north" and labels["instance"] == f"poller-{k}", labels


def _plant(tmp_path, k: int, inventory: str) -> str:
    path = tmp_path / f"plant{k}.toml"
    path.write_text(f'[poll]\nsite = "north"\ninstance = "poller-{k}"\ninterval = 1\n' + inventory)
    return str(path)
