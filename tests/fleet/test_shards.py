"""poll --shard K/N and exporter --shard K/N (issue 44): each of N pollers takes the links whose
name hashes to its K, as Prometheus' hashmod relabelling hashes them, so pollers and a scrape
config split one inventory alike; a link's devices go with it."""

from __future__ import annotations

import json
import shutil
import struct
import subprocess
import urllib.request

import pytest
from helpers.checks import assert_one_error_line, wait_until
from helpers.exporter import exporting
from helpers.run import mbtool_env, run_cli, start_mbtool
from helpers.sockets import RawResponder, free_port

from mbtool.plant.inventory import shard_of

LINKS = [f"bus{i}" for i in range(20)]


def answer(request: bytes) -> bytes:
    """A read of holding registers answered with one register, 1, whatever it asked."""
    tid, _, _, unit = struct.unpack(">HHHB", request[:7])
    return struct.pack(">HHHB", tid, 0, 5, unit) + bytes([3, 2, 0, 1])


@pytest.fixture
def devices():
    servers = [RawResponder(answer) for _ in LINKS]
    yield servers
    for server in servers:
        server.close()


def inventory(tmp_path, servers) -> str:
    path = tmp_path / "plant.toml"
    path.write_text(
        "".join(
            f'[links.{name}]\ntarget = "tcp://127.0.0.1:{server.port}"\ntimeout = 2\n'
            f'[devices.d{name}]\nlink = "{name}"\nread = ["40001"]\n'
            for name, server in zip(LINKS, servers, strict=True)
        )
    )
    return str(path)


def test_two_shards_poll_every_link_exactly_once_between_them(tmp_path, devices):
    path = inventory(tmp_path, devices)
    shards = [start_mbtool("poll", path, "--once", "-o", "json", "--shard", f"{k}/2") for k in (0, 1)]
    polled = []
    for proc in shards:
        out, err = proc.communicate(timeout=30)
        assert proc.returncode == 0, err
        polled.append({json.loads(line)["device"][1:] for line in out.splitlines()})
    assert polled[0] and polled[1] and not polled[0] & polled[1]
    assert polled[0] | polled[1] == set(LINKS)
    for name, server in zip(LINKS, devices, strict=True):  # the devices' own logs of requests
        assert len(server.requests) == 1, (name, server.requests)


def test_the_exporters_shard_polls_and_shows_its_links_alone(tmp_path, devices):
    path = inventory(tmp_path, devices)
    with exporting(path, "--shard", "1/2", tmp_path=tmp_path) as running:
        assert wait_until(lambda: "modbus_polls_total" in running.get("/metrics")[2], 10)
        text = running.get("/metrics")[2]
    shown = {
        line.split('link="')[1].split('"')[0]
        for line in text.splitlines()
        if line.startswith("modbus_link_up{")
    }
    assert shown == {name for name in LINKS if shard_of(name, 2) == 1}
    for name, server in zip(LINKS, devices, strict=True):
        assert bool(server.requests) == (name in shown), name


def test_a_shard_out_of_range_or_malformed_is_exit_2(tmp_path, devices):
    path = inventory(tmp_path, devices)
    for shard in ("2/2", "0/0", "a/2", "1", "-1/2"):
        line = assert_one_error_line(run_cli("poll", path, "--once", "--shard", shard), 2)
        assert "--shard" in line
    assert all(server.received_bytes(0) == b"" for server in devices)


def test_a_shard_of_no_link_is_exit_2_with_nothing_opened(tmp_path, devices):
    path = tmp_path / "plant.toml"
    port = devices[0].port
    path.write_text(
        f'[links.bus0]\ntarget = "tcp://127.0.0.1:{port}"\n[devices.d]\nlink = "bus0"\nread = ["40001"]\n'
    )
    res = [run_cli("poll", path, "--once", "--shard", f"{k}/2") for k in (0, 1)]
    empty = next(r for r in res if r.returncode == 2)
    assert "no link of" in assert_one_error_line(empty, 2)


@pytest.mark.skipif(shutil.which("prometheus") is None, reason="Debian's prometheus is not installed")
def test_prometheus_hashmod_picks_the_same_split(tmp_path):
    """Prometheus, given static targets labelled with the links' names and a hashmod + keep
    relabelling of shard 1 of 3, keeps the links mbtool's --shard 1/3 polls."""
    names = [*LINKS, "north-gw", "bus/ü", "a b"]
    config = tmp_path / "prometheus.yml"
    config.write_text(
        "scrape_configs:\n  - job_name: modbus\n    scrape_interval: 1h\n    static_configs:\n"
        + "".join(
            f'      - targets: ["127.0.0.1:{9 + i}"]\n        labels: {{link: {json.dumps(n)}}}\n'
            for i, n in enumerate(names)
        )
        + "    relabel_configs:\n"
        "      - {source_labels: [link], modulus: 3, target_label: __tmp_shard, action: hashmod}\n"
        "      - {source_labels: [__tmp_shard], regex: '1', action: keep}\n"
    )
    port = free_port()
    proc = subprocess.Popen(
        ["prometheus", f"--config.file={config}", f"--web.listen-address=127.0.0.1:{port}",
         f"--storage.tsdb.path={tmp_path / 'data'}"],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=mbtool_env(),
    )  # fmt: skip
    try:
        targets: list = []

        def kept() -> bool:
            try:
                with urllib.request.urlopen(f"http://127.0.0.1:{port}/api/v1/targets", timeout=2) as response:
                    targets[:] = json.load(response)["data"]["activeTargets"]
            except OSError:
                return False
            return bool(targets)

        assert wait_until(kept, 30, 0.2), "prometheus did not serve its targets"
    finally:
        proc.terminate()
        proc.wait(10)
    kept = {t["labels"]["link"] for t in targets}
    assert 0 < len(kept) < len(names) and kept == {n for n in names if shard_of(n, 3) == 1}
