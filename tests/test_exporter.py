"""mbtool exporter: a Prometheus exporter in two modes (issue 32).

Multi-target: GET /modbus?target=...&module=...&unit=... reads a register map from the
target on each scrape, within the deadline the scraper sends; a device that fails is HTTP
200 with modbus_up 0 and the reason, a target no --allow-target pattern allows is refused
with nothing opened.  Inventory: the plant is polled as `mbtool poll` polls it, and
/metrics serves the latest values from memory.  Every exposition here is read back with
prometheus_client's own parser; tests/test_exporter_prometheus.py has Prometheus itself
scrape the exporter.
"""

from __future__ import annotations

import contextlib
import math
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
import urllib.error
import urllib.request
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import urlencode

import pytest
from conftest import REPO_ROOT, first_line, mbtool_env, run_mbtool, signals_as_from_a_shell
from test_serve import serve

from mbtool.errors import NoResponse
from mbtool.plant.stats import RTT_BUCKETS, Stats

pytestmark = pytest.mark.timeout(120)

# --- the round-trip histogram's buckets -------------------------------------------------------


def test_round_trips_land_in_the_fixed_buckets_each_counted_up_to_its_bound():
    assert RTT_BUCKETS[0] == 0.001 and RTT_BUCKETS[-1] == 10.0  # 1 ms ... 10 s, fixed
    stats = Stats()
    for seconds in (0.0004, 0.001, 0.0011, 0.3, 12.0):
        stats.round_trip(seconds)
    buckets = dict(stats.rtt_histogram())
    assert buckets[0.001] == 2  # "le": up to the bound, the bound itself included
    assert buckets[0.0025] == 3
    assert buckets[0.25] == 3 and buckets[0.5] == 4
    assert buckets[10.0] == 4 and buckets[math.inf] == 5  # past 10 s only in +Inf
    link = Stats()
    link.add(stats)
    link.add(stats)
    assert dict(link.rtt_histogram())[math.inf] == 10 and link.rtt_count == 10


# --- the exporter as a user runs it ------------------------------------------------------------

METER_DATA = REPO_ROOT / "examples" / "energy-meter-data.toml"
METER_MAP = REPO_ROOT / "examples" / "energy-meter.toml"


@dataclass
class Running:
    proc: subprocess.Popen
    url: str  # http://127.0.0.1:PORT
    line: str  # the first line it printed
    stderr: Path

    def get(self, path: str, headers: dict[str, str] | None = None, timeout: float = 30.0):
        return http_get(self.url + path, headers, timeout)


@contextlib.contextmanager
def exporting(*args: str, tmp_path: Path):
    """mbtool exporter ARGS on a free loopback port; stopped by SIGTERM, which must end it with
    exit 0 and no traceback."""
    stderr = tmp_path / f"exporter-{len(list(tmp_path.glob('exporter-*')))}.err"
    with open(stderr, "w") as err:
        proc = subprocess.Popen(
            [sys.executable, "-m", "mbtool", "exporter", "--listen", "127.0.0.1:0", *map(str, args)],
            cwd=REPO_ROOT,
            env=mbtool_env(),
            preexec_fn=signals_as_from_a_shell,
            stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=err,
        )
    try:
        line = first_line(proc, "exporting on ")
        yield Running(proc, re.search(r"http://[^ ]+", line)[0], line, stderr)
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
        try:
            proc.communicate(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.communicate(timeout=5)
            pytest.fail("the exporter did not stop on SIGTERM within 10 s")
        assert proc.returncode == 0, stderr.read_text()
        assert "Traceback" not in stderr.read_text()


def http_get(url: str, headers: dict[str, str] | None = None, timeout: float = 30.0) -> tuple[int, str, str]:
    """(status, content type, body) of a GET, whatever the status."""
    opener = urllib.request.build_opener(urllib.request.ProxyHandler({}))  # loopback, never a proxy
    try:
        with opener.open(urllib.request.Request(url, headers=headers or {}), timeout=timeout) as response:
            return response.status, response.headers["Content-Type"], response.read().decode()
    except urllib.error.HTTPError as error:
        return error.code, error.headers["Content-Type"], error.read().decode()


def samples(text: str) -> dict[tuple[str, frozenset], float]:
    """Every sample of an exposition, read by prometheus_client's parser: (name, labels) -> value."""
    from prometheus_client.parser import text_string_to_metric_families

    return {
        (sample.name, frozenset(sample.labels.items())): sample.value
        for family in text_string_to_metric_families(text)
        for sample in family.samples
    }


def value(text: str, name: str, **labels: str) -> float:
    found = samples(text)
    key = (name, frozenset(labels.items()))
    assert key in found, f"no {name}{labels} in:\n{text}"
    return found[key]


def one_family_each(text: str) -> None:
    """Each family once: one HELP and one TYPE line a name (two would be no exposition)."""
    names = re.findall(r"^# TYPE (\S+) ", text, re.M)
    assert len(names) == len(set(names)), sorted(n for n in names if names.count(n) > 1)


@pytest.fixture(scope="module")
def meter(tmp_path_factory):
    """mbtool serve holding the energy meter's data (examples/), and a maps folder with its map."""
    maps = tmp_path_factory.mktemp("maps")
    shutil.copy(METER_MAP, maps / "energy-meter.toml")
    with serve("--data", str(METER_DATA)) as server:
        server.maps = maps
        yield server


# --- multi-target: /modbus -----------------------------------------------------------------------


def test_a_scrape_reads_the_module_from_the_target_as_read_m_does(meter, tmp_path):
    read_m = run_mbtool("read", "-m", METER_MAP, "-p", meter.target, "-o", "prom")
    assert read_m.returncode == 0, read_m
    expected = {
        (name, dict(labels)["ref"]): number
        for (name, labels), number in samples(read_m.stdout).items()
        if "ref" in dict(labels)
    }
    assert len(expected) == 10
    with exporting(
        "--maps", meter.maps, "--allow-target", "tcp://127.0.0.1:*", tmp_path=tmp_path
    ) as exporter:
        status, kind, text = exporter.get(f"/modbus?target={meter.target}&module=energy-meter&unit=1")
    assert status == 200 and kind.startswith("text/plain; version=0.0.4"), text
    one_family_each(text)
    got = {
        (name, dict(labels)["ref"]): number
        for (name, labels), number in samples(text).items()
        if "ref" in dict(labels)
    }
    assert got == expected
    assert value(text, "modbus_voltage_l1", unit="1", ref="30001") == 230.1
    assert value(text, "modbus_up", unit="1") == 1
    assert not [key for key in samples(text) if key[0] == "modbus_error_info"]


def test_a_device_that_fails_is_http_200_with_modbus_up_0_and_the_reason(
    meter, tmp_path, silent_server, refused_port
):
    deadline = {"X-Prometheus-Scrape-Timeout-Seconds": "1.5"}
    with (
        serve("--exception", "4:4", "--exception", "3:4", "--exception", "1:4") as refusing,
        serve("--exception", "4:4", "--data", str(METER_DATA)) as partly,
    ):
        with exporting(
            "--maps", meter.maps, "--allow-target", "tcp://127.0.0.1:*", tmp_path=tmp_path
        ) as exporter:
            cases = {
                f"tcp://127.0.0.1:{refused_port}": ("connection", 0, "cannot connect"),
                silent_server.tcp_target: ("timeout", 0, "no response from unit 1"),
                meter.target + "&unit=9": ("timeout", 0, "no response from unit 9"),
                refusing.target: ("exception", 0, "exception 04"),
                partly.target: ("partial", 1, "5 of 10 points read"),
            }
            for target, (kind, up, reason) in cases.items():
                began = time.monotonic()
                status, _, text = exporter.get(f"/modbus?target={target}&module=energy-meter", deadline)
                took = time.monotonic() - began
                assert status == 200, text
                one_family_each(text)
                unit = "9" if "unit=9" in target else "1"
                assert value(text, "modbus_up", unit=unit) == up, text
                (info,) = [dict(labels) for name, labels in samples(text) if name == "modbus_error_info"]
                assert info["kind"] == kind and reason in info["reason"], info
                assert took < 1.5 + 1.0, f"{target}: {took:.2f} s past a 1.5 s deadline"
            # A device that fails shows no value: one read before would be taken as current.
            status, _, text = exporter.get(
                f"/modbus?target={silent_server.tcp_target}&module=energy-meter", deadline
            )
            assert not [key for key in samples(text) if key[0] == "modbus_voltage_l1"]


def test_the_read_ends_within_the_deadline_the_scraper_sends(meter, tmp_path):
    """A device slower than the scrape's deadline: the answer comes before the deadline, with
    modbus_up 0, so Prometheus keeps why rather than a scrape that timed out."""
    with serve("--delay", "3", "--data", str(METER_DATA)) as slow:
        with exporting(
            "--maps", meter.maps, "--allow-target", "tcp://127.0.0.1:*", tmp_path=tmp_path
        ) as exporter:
            for deadline in ("1", "2.5"):
                began = time.monotonic()
                status, _, text = exporter.get(
                    f"/modbus?target={slow.target}&module=energy-meter",
                    {"X-Prometheus-Scrape-Timeout-Seconds": deadline},
                )
                took = time.monotonic() - began
                assert status == 200 and value(text, "modbus_up", unit="1") == 0, text
                (info,) = [dict(labels) for name, labels in samples(text) if name == "modbus_error_info"]
                assert info["kind"] == "timeout", info
                assert took < float(deadline), f"answered {took:.2f} s after a {deadline} s deadline"
                assert value(text, "modbus_scrape_duration_seconds", unit="1") <= float(deadline) - 0.25 + 0.1


def test_a_target_no_pattern_allows_is_refused_with_one_line_and_nothing_opened(
    meter, tmp_path, silent_server
):
    with exporting(
        "--maps", meter.maps, "--allow-target", "tcp://192.0.2.*:502", "--allow-target", meter.target,
        tmp_path=tmp_path,
    ) as exporter:  # fmt: skip
        for target in (
            silent_server.tcp_target,
            silent_server.socket_target,
            "tcp://127.0.0.1",
            "/dev/ttyS0",
        ):
            status, kind, text = exporter.get(
                f"/modbus?{urlencode({'target': target, 'module': 'energy-meter'})}"
            )
            assert status == 403 and kind.startswith("text/plain"), text
            assert text == f"target {target} is not allowed: no --allow-target pattern matches it\n"
        status, _, text = exporter.get(f"/modbus?target={meter.target}&module=energy-meter")
        assert status == 200 and value(text, "modbus_up", unit="1") == 1
    assert silent_server.connections == 0 and silent_server.received_bytes() == b""


@pytest.mark.parametrize(
    "query, status, words",
    [
        ("module=energy-meter", 400, "no target"),
        ("target={t}", 400, "no module"),
        ("target={t}&module=../energy-meter", 400, "without a folder"),
        ("target={t}&module=sub/energy-meter", 400, "without a folder"),
        ("target={t}&module=nosuch", 400, "has no nosuch.toml nor nosuch.csv"),
        ("target={t}&module=energy-meter&unit=256", 400, "unit '256': a unit id is a number, 0..255"),
        ("target={t}&module=energy-meter&unit=x", 400, "unit 'x'"),
        ("target={t}&module=energy-meter&module=energy-meter", 400, "module is given 2 times"),
        ("target={s}&module=energy-meter&unit=0", 400, "unit 0 is broadcast"),
        ("target=tcp://127.0.0.1:99999&module=energy-meter", 400, "target tcp://127.0.0.1:99999"),
        ("target={t}&module=clash", 500, "point up: its metric, modbus_up, is one the exporter has"),
    ],
    ids=["no-target", "no-module", "dot-dot", "slash", "unknown", "unit-range", "unit-text", "twice",
         "broadcast", "bad-target", "clash"],
)  # fmt: skip
def test_a_bad_scrape_is_one_line_with_its_status_and_nothing_opened(
    meter, tmp_path, silent_server, query, status, words
):
    (meter.maps / "clash.toml").write_text("[points.up]\nref = 40001\n")
    (tmp_path / "energy-meter.toml").write_text(METER_MAP.read_text())  # outside the maps folder
    asked = query.format(t=silent_server.tcp_target, s=silent_server.socket_target)
    with exporting("--maps", meter.maps, "--allow-target", "*://127.0.0.1:*", tmp_path=tmp_path) as exporter:
        got, kind, text = exporter.get(f"/modbus?{asked}")
    assert got == status and kind.startswith("text/plain"), text
    assert words in text and text.count("\n") == 1, text
    assert silent_server.connections == 0


def test_scrapes_of_one_target_take_turns_and_of_others_run_at_once(monkeypatch):
    """One scrape of a target at a time (a bus has one master; many devices take one
    connection), in the exporter's own process."""
    from mbtool.cli.commands import exporter

    running: dict[str, int] = {"all": 0}
    most: dict[str, int] = {}
    lock = threading.Lock()

    def read(connection, register_map, deadline, budget):
        with lock:
            for key in (connection.port, "all"):
                running[key] = running.get(key, 0) + 1
                most[key] = max(most.get(key, 0), running[key])
        time.sleep(0.2)
        with lock:
            running[connection.port] -= 1
            running["all"] -= 1
        return None, NoResponse("silence"), "timeout"

    monkeypatch.setattr(exporter, "_read_map", read)
    modules = exporter.Modules(METER_MAP.parent, {})
    scraper = exporter.TargetScraper(modules, ["tcp://192.0.2.*"], {}, 1.0, 0)
    threads = [
        threading.Thread(
            target=scraper.scrape, args=(f"target=tcp://192.0.2.{1 + n % 2}:502&module=energy-meter", "5")
        )
        for n in range(6)
    ]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(30)
    assert most == {"tcp://192.0.2.1:502": 1, "tcp://192.0.2.2:502": 1, "all": 2}
    assert max(running.values()) == 0
