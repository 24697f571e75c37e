"""mbtool exporter: a Prometheus exporter in two modes (issue 32).

Multi-target: GET /modbus?target=...&module=...&unit=... reads a register map from the
target on each scrape, within the deadline the scraper sends; a device that fails is HTTP
200 with modbus_up 0 and the reason, a target no --allow-target pattern allows is refused
with nothing opened.  Inventory: the plant is polled as `mbtool poll` polls it, and
/metrics serves the latest values from memory.  Every exposition here is read back with
prometheus_client's own parser; tests/e2e/test_exporter_prometheus.py has Prometheus itself
scrape the exporter.
"""

from __future__ import annotations

import os
import re
import shutil
import socket
import subprocess
import sys
import threading
import time
import tty
from urllib.parse import urlencode

import pytest
from helpers.checks import assert_one_error_line
from helpers.exporter import METER_DATA, METER_MAP, Running, exporting
from helpers.prometheus import promtool_check
from helpers.run import REPO_ROOT, run_cli
from helpers.served import serve

from mbtool.errors import NoResponse

pytestmark = pytest.mark.timeout(120)

# --- the exporter as a user runs it ------------------------------------------------------------


def samples(text: str) -> dict[tuple[str, frozenset], float]:
    """Every sample of an exposition, read by prometheus_client's parser: (name, labels) -> value."""
    from prometheus_client.parser import text_string_to_metric_families

    return {
        (sample.name, frozenset(sample.labels.items())): sample.value
        for family in text_string_to_metric_families(text)
        for sample in family.samples
    }


def value(text: str, name: str, **labels: str) -> float:
    """A sample's value by its labels; a plant's samples carry the poller's instance label too
    (the host name, as no inventory here names one)."""
    found = samples(text)
    key = (name, frozenset(labels.items()))
    if key not in found:
        key = (name, frozenset((labels | {"instance": os.uname().nodename}).items()))
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
    read_m = run_cli("read", "-m", METER_MAP, "-p", meter.target, "-o", "prom")
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
    modbus_up 0, so Prometheus keeps why rather than a scrape that timed out.  The timeout
    for each reply (5 s) would have waited for the device's (3 s): the deadline cuts it."""
    with serve("--delay", "3", "--data", str(METER_DATA)) as slow:
        with exporting(
            "--maps", meter.maps, "--allow-target", "tcp://127.0.0.1:*", "--timeout", "5", tmp_path=tmp_path
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
                waited = float(re.search(r"no response from unit 1 within ([0-9.]+) s", info["reason"])[1])
                assert waited <= float(deadline) - 0.25, info  # the deadline's, not the 5 s
                assert took < float(deadline) + 1.0, f"answered {took:.2f} s after a {deadline} s deadline"


def test_a_scrape_timeout_past_the_exporters_maximum_is_clamped_to_it(meter, tmp_path):
    """Issue 40.15: a header of 9.3e9 s was HTTP 500 'internal error: OverflowError'."""
    from mbtool.cli.commands.exporter import MAX_SCRAPE_TIMEOUT, scrape_budget

    with exporting(
        "--maps", meter.maps, "--allow-target", "tcp://127.0.0.1:*", tmp_path=tmp_path
    ) as exporter:
        for seconds in ("9.3e9", "1e300", str(MAX_SCRAPE_TIMEOUT * 2)):
            status, _, text = exporter.get(
                f"/modbus?target={meter.target}&module=energy-meter",
                {"X-Prometheus-Scrape-Timeout-Seconds": seconds},
            )
            assert status == 200 and value(text, "modbus_up", unit="1") == 1, text
    assert scrape_budget("9.3e9") == scrape_budget(str(MAX_SCRAPE_TIMEOUT)) < MAX_SCRAPE_TIMEOUT


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


def test_a_scrape_never_opens_a_pyserial_url_handler_nor_a_file_outside_dev(meter, tmp_path):
    """Issue 40.1: a pattern that starts with a wildcard matched spy://...?file=PATH, and one
    GET truncated the file; a device pattern let ../.. through.  The target is parsed first:
    network links and serial devices are opened, pyserial's URL handlers never."""
    victim = tmp_path / "victim"
    victim.write_text("kept\n")
    ports = tmp_path / "ports"
    ports.mkdir()
    with exporting(
        "--maps", meter.maps, "--allow-target", "*", "--allow-target", f"{ports}/*",
        "--allow-target", "/dev/serial/by-id/*", tmp_path=tmp_path,
    ) as exporter:  # fmt: skip
        for target in (
            f"spy://loop://?file={victim}",
            "loop://",
            "alt://loop://?class=Serial",
            "hwgrep://.*",
            "rfc2217://127.0.0.1:1",  # not without a pattern that names rfc2217:// itself
            "sim://",
            f"{ports}/../victim",
            "/dev/serial/by-id/../../../etc/hostname",
        ):
            status, _, text = exporter.get(
                f"/modbus?{urlencode({'target': target, 'module': 'energy-meter'})}"
            )
            assert status == 403, (target, text)
            assert text.startswith(f"target {target} ") and text.count("\n") == 1, text
        # A pattern matches the target as the resolver reads it: 127.0.0.01 is 127.0.0.1.
        port = meter.target.rsplit(":", 1)[1]
        status, _, text = exporter.get(f"/modbus?target=TCP://127.0.0.01:{port}/&module=energy-meter")
        assert status == 200 and value(text, "modbus_up", unit="1") == 1, text
    assert victim.read_text() == "kept\n"


def test_an_allow_target_pattern_matches_the_normalised_target(meter, tmp_path):
    port = meter.target.rsplit(":", 1)[1]
    with exporting(
        "--maps", meter.maps, "--allow-target", f"tcp://127.0.0.1:{port}", tmp_path=tmp_path
    ) as exporter:
        for target in (f"tcp://127.1:{port}", f"tcp://0x7f.0.0.1:{port}", f"tcp://127.0.0.1:{port}/"):
            status, _, text = exporter.get(f"/modbus?target={target}&module=energy-meter")
            assert status == 200 and value(text, "modbus_up", unit="1") == 1, (target, text)
        status, _, text = exporter.get(f"/modbus?target=tcp://127.0.0.2:{port}&module=energy-meter")
        assert status == 403, text


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
        ("target=loop://?x=1&module=energy-meter", 400, "loop:// takes no option 'x'"),
        ("target=hwgrep://((&module=energy-meter", 400, "is no regular expression"),
        ("target={t}&module=clash", 500, "point up: its metric, modbus_up, is one the exporter has"),
        ("target=tcp://10.0.0.1%0A:502&module=energy-meter", 403, "target 'tcp://10.0.0.1\\n:502' is not allowed"),
        ("target={t}&module=energy-meter&unit=%C2%B2", 400, "unit '²': a unit id is a number"),
        ("target={t}&module=energy-meter&unit=" + "9" * 5000, 400, "a unit id is a number, 0..255"),
    ],
    ids=["no-target", "no-module", "dot-dot", "slash", "unknown", "unit-range", "unit-text", "twice",
         "broadcast", "bad-target", "loop-option", "hwgrep-regexp", "clash", "newline", "unicode-digit", "long-unit"],
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


def _counting_read(monkeypatch, pause):
    """_read_map replaced by one that takes ``pause(key)`` seconds and counts the reads under
    way by the link's normalised target (key): the most at once of each."""
    from mbtool.cli.commands import exporter
    from mbtool.link.transport import parse_target

    running: dict[str, int] = {}
    most: dict[str, int] = {}
    lock = threading.Lock()

    def read(connection, register_map, deadline, budget):
        key = str(parse_target(connection.port).normalised())
        with lock:
            running[key] = running.get(key, 0) + 1
            most[key] = max(most.get(key, 0), running[key])
        time.sleep(pause(key))
        with lock:
            running[key] -= 1
        return None, NoResponse("silence"), "timeout"

    monkeypatch.setattr(exporter, "_read_map", read)
    return most


def test_other_spellings_of_one_target_take_turns_too(monkeypatch):
    """Issue 40.2: the locks were keyed by the raw string, and six spellings of one address
    made six connections at once."""
    from mbtool.cli.commands import exporter

    most = _counting_read(monkeypatch, lambda key: 0.2)
    scraper = exporter.TargetScraper(exporter.Modules(METER_MAP.parent, {}), ["tcp://127.*"], {}, 1.0, 0)
    spellings = ["127.0.0.1", "127.0.0.01", "127.1", "0x7f.0.0.1", "0177.0.0.1", "2130706433"]
    threads = [
        threading.Thread(target=scraper.scrape, args=(f"target=tcp://{host}:1502&module=energy-meter", "5"))
        for host in spellings
    ]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(30)
    assert most == {"tcp://127.0.0.1:1502": 1}


def test_localhost_and_the_loopback_addresses_are_one_target_and_take_turns(monkeypatch):
    """localhost is the loopback (RFC 6761 6.3), 127.0.0.1 or ::1, whichever the device
    listens on: three spellings were three links, and so two masters at once on one device
    (a gateway's bus).  Known without a lookup: no DNS a scrape."""
    from mbtool.cli.commands import exporter

    running, most = [0], [0]
    lock = threading.Lock()

    def read(connection, register_map, deadline, budget):
        with lock:
            running[0] += 1
            most[0] = max(most[0], running[0])
        time.sleep(0.2)
        with lock:
            running[0] -= 1
        return None, NoResponse("silence"), "timeout"

    monkeypatch.setattr(exporter, "_read_map", read)
    patterns = ["tcp://127.*", "tcp://localhost:*", "tcp://[[]::1]:*"]
    scraper = exporter.TargetScraper(exporter.Modules(METER_MAP.parent, {}), patterns, {}, 1.0, 0)
    spellings = ["localhost", "127.0.0.1", "[::1]", "LOCALHOST."]
    statuses = []
    threads = [
        threading.Thread(
            target=lambda host=host: statuses.append(
                scraper.scrape(f"target=tcp://{host}:1502&module=energy-meter", "5")[0]
            )
        )
        for host in spellings
    ]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(30)
    assert statuses == [200] * len(spellings) and most == [1]


def test_the_table_of_locks_is_bounded_and_keeps_a_lock_in_use(monkeypatch):
    """Issue 40.2: 2,000 GETs of as many targets took the exporter from 29 to 105 MB.  The
    table keeps the LOCKS_KEPT used last, never one a scrape holds or waits on: a second
    scrape of a target under way waits for the first, however many others came between."""
    from mbtool.cli.commands import exporter

    held = "tcp://10.9.9.9:502"
    most = _counting_read(monkeypatch, lambda key: 0.5 if key == held else 0.0)
    scraper = exporter.TargetScraper(exporter.Modules(METER_MAP.parent, {}), ["tcp://10.*"], {}, 1.0, 0)
    first = threading.Thread(target=scraper.scrape, args=(f"target={held}&module=energy-meter", "5"))
    first.start()
    time.sleep(0.1)
    for n in range(2000):
        scraper.scrape(f"target=tcp://10.{n // 250}.{n % 250}.1:502&module=energy-meter", "5")
        assert len(scraper.locks) <= exporter.LOCKS_KEPT
    second = threading.Thread(target=scraper.scrape, args=(f"target={held}&module=energy-meter", "5"))
    second.start()
    first.join(30)
    second.join(30)
    assert most[held] == 1 and len(most) == 2001


# --- inventory: /metrics from memory --------------------------------------------------------------


def wait_for(exporter: Running, ready, seconds: float = 30.0) -> str:
    """/metrics once ``ready(text)`` holds; the test fails with the last text after ``seconds``."""
    end = time.monotonic() + seconds
    text = ""
    while time.monotonic() < end:
        status, _, text = exporter.get("/metrics")
        assert status == 200, text
        try:
            if ready(text):
                return text
        except AssertionError:
            pass
        time.sleep(0.2)
    pytest.fail(f"/metrics not ready after {seconds} s:\n{text}\n{exporter.stderr.read_text()}")


def test_inventory_metrics_are_every_devices_latest_values_and_statistics(meter, tmp_path, refused_port):
    shutil.copy(METER_MAP, tmp_path / "meter.toml")
    plant = tmp_path / "plant.toml"
    plant.write_text(f"""
[poll]
interval = 0.3
offline_after = 1

[links.gw]
target = "{meter.target}"
timeout = 0.3

[links.lost]
target = "tcp://127.0.0.1:{refused_port}"

[devices.meter1]
link = "gw"
unit = 1
map = "meter.toml"
tags = {{ site = "north" }}

[devices.dead]
link = "gw"
unit = 9
read = ["40001 1"]

[devices.gone]
link = "lost"
read = ["40001 1"]
""")
    with exporting(plant, tmp_path=tmp_path) as exporter:
        assert "3 devices of" in exporter.line and "on 2 links" in exporter.line
        text = wait_for(
            exporter,
            lambda text: (
                value(text, "modbus_up", device="meter1", site="north") == 1
                and value(text, "modbus_transactions_total", device="dead", outcome="timeout") >= 2
                and value(text, "modbus_link_open_failures_total", link="lost") >= 1
            ),
        )
        one_family_each(text)
        promtool_check(text)  # the example map's points as gauges Prometheus's lint accepts
        assert value(text, "modbus_voltage_l1", device="meter1", site="north", ref="30001") == 230.1
        assert value(text, "modbus_tariff", device="meter1", site="north", ref="40001") == 1  # "day"
        assert value(text, "modbus_up", device="dead") == 0 and value(text, "modbus_up", device="gone") == 0
        assert (
            abs(
                value(text, "modbus_last_success_timestamp_seconds", device="meter1", site="north")
                - time.time()
            )
            < 60
        )
        answered = value(text, "modbus_transactions_total", device="meter1", outcome="answered")
        assert answered >= 3  # three requests a poll: input registers, holding registers, coils
        # Every reply's round trip is in the histogram, whose buckets count up to +Inf, but for
        # the replies that came while mbtool was busy, whose arrival is not known (counted apart).
        timed = answered - value(text, "modbus_untimed_replies_total", device="meter1")
        assert value(text, "modbus_request_duration_seconds_count", device="meter1") == timed
        assert value(text, "modbus_request_duration_seconds_bucket", device="meter1", le="+Inf") == timed
        assert value(text, "modbus_request_duration_seconds_bucket", device="meter1", le="10.0") == timed
        assert value(text, "modbus_polls_total", device="dead") == value(
            text, "modbus_failed_polls_total", device="dead"
        )
        assert (
            value(text, "modbus_link_up", link="gw") == 1 and value(text, "modbus_link_up", link="lost") == 0
        )
        link_answered = value(text, "modbus_link_transactions_total", link="gw", outcome="answered")
        assert link_answered >= answered
        link_timed = link_answered - value(text, "modbus_link_untimed_replies_total", link="gw")
        assert value(text, "modbus_link_request_duration_seconds_count", link="gw") == link_timed
        # The exporter's own process, from prometheus_client's default registry.
        assert value(text, "process_cpu_seconds_total") > 0
        assert [key for key in samples(text) if key[0] == "python_info"]
        # No value for a device that is down: the last one read would be scraped as current.
        assert not [
            key for key in samples(text) if dict(key[1]).get("device") == "dead" and key[0] == "modbus_value"
        ]
    events = exporter.stderr.read_text()
    assert "dead offline: no response from unit 9" in events and "link lost offline: cannot connect" in events


def test_modbus_of_a_link_the_inventory_polls_is_refused_with_the_reason(meter, tmp_path, silent_server):
    """Issues 40.10 and 39.10: /modbus of a TCP link the inventory polls opened a second master
    beside the plant's, and of a serial link it polls said 'port busy (another program has it
    open)', the other program being the exporter itself.  Refused, whatever the spelling; a
    link of the inventory that no device uses is read with its settings, as before."""
    master, slave = os.openpty()
    tty.setraw(master)
    serial_path = os.ttyname(slave)
    port = silent_server.port
    plant = tmp_path / "plant.toml"
    plant.write_text(f"""
[poll]
interval = 0.2

[links.gw]
target = "tcp://127.0.0.1:{port}"
timeout = 0.2

[links.bus1]
target = "{serial_path}"
timeout = 0.2

[links.spare]
target = "{meter.target}"

[devices.meter]
link = "gw"
read = ["40001 1"]

[devices.pump]
link = "bus1"
read = ["40001 1"]
""")
    try:
        with exporting(
            plant, "--maps", meter.maps, "--allow-target", "tcp://127.0.0.1:*",
            "--allow-target", "/dev/pts/*", tmp_path=tmp_path,
        ) as exporter:  # fmt: skip
            wait_for(exporter, lambda text: value(text, "modbus_polls_total", device="pump") >= 1)
            for target, link in (
                (f"tcp://127.0.0.1:{port}", "gw"),
                (f"TCP://127.0.0.01:{port}/", "gw"),
                (serial_path, "bus1"),
            ):
                status, kind, text = exporter.get(
                    f"/modbus?{urlencode({'target': target, 'module': 'energy-meter'})}"
                )
                assert (status, kind.split(";")[0]) == (409, "text/plain"), text
                assert text == f"link {link} is polled by this exporter's inventory: scrape /metrics\n"
            status, _, text = exporter.get(f"/modbus?target={meter.target}&module=energy-meter")
            assert status == 200 and value(text, "modbus_up", unit="1") == 1, text
        assert silent_server.connections == 1  # the plant's own, and no second master
    finally:
        os.close(master)
        os.close(slave)


def test_an_inventory_scrape_answers_at_once_while_a_slow_device_is_polled(tmp_path):
    """Scrapes never touch the bus: a device that takes 3 s a reply is polled while scrapes
    come, and each is answered from what the last poll left."""
    with serve("--delay", "3", "--data", str(METER_DATA)) as slow:
        plant = tmp_path / "plant.toml"
        plant.write_text(f"""
[poll]
interval = 0.1

[links.slow]
target = "{slow.target}"
timeout = 10

[devices.meter]
link = "slow"
read = ["40001 1"]
""")
        with exporting(plant, tmp_path=tmp_path) as exporter:
            wait_for(exporter, lambda text: value(text, "modbus_polls_total", device="meter") >= 1)
            took = []
            for _ in range(30):  # 3 s and more: a poll is under way all along
                began = time.monotonic()
                status, _, text = exporter.get("/metrics")
                took.append(time.monotonic() - began)
                assert (
                    status == 200
                    and value(text, "modbus_value", device="meter", table="holding", address="0", ref="40001")
                    == 1
                )
                time.sleep(0.1)
            assert max(took) < 1.5, took  # never the 3 s a reply takes


def test_several_scrapers_at_once_each_get_a_whole_exposition(meter, tmp_path):
    plant = tmp_path / "plant.toml"
    shutil.copy(METER_MAP, tmp_path / "meter.toml")
    plant.write_text(
        "[poll]\ninterval = 0.05\n"
        + f'[links.gw]\ntarget = "{meter.target}"\n'
        + "".join(f'[devices.m{n}]\nlink = "gw"\nmap = "meter.toml"\n' for n in range(5))
    )
    with exporting(plant, tmp_path=tmp_path) as exporter:
        wait_for(exporter, lambda text: all(value(text, "modbus_up", device=f"m{n}") == 1 for n in range(5)))
        texts: list[str] = []

        def scrape() -> None:
            for _ in range(20):
                texts.append(exporter.get("/metrics")[2])

        threads = [threading.Thread(target=scrape) for _ in range(6)]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join(60)
    assert len(texts) == 120
    for text in texts:
        one_family_each(text)
        for n in range(5):
            assert value(text, "modbus_voltage_l1", device=f"m{n}", ref="30001") == 230.1


def test_the_plants_exposition_shows_every_device_before_its_first_poll_and_each_family_once():
    """In-process, on examples/plant.toml (sim://): what PlantMetrics joins is one exposition."""
    from mbtool.cli.commands.exporter import PlantMetrics
    from mbtool.cli.program import register_schemes
    from mbtool.plant.inventory import load_inventory
    from mbtool.plant.schedule import Plant

    register_schemes()  # sim://, as main() does
    plant = load_inventory(str(REPO_ROOT / "examples" / "plant.toml"))
    metrics = PlantMetrics()
    runner = Plant(plant.links, plant.devices, metrics.report, rounds=1)
    metrics.watch(runner)
    before = metrics.text().decode()
    one_family_each(before)
    assert {
        name for name in ("meter1", "plc", "spare") if value(before, "modbus_up", **_labels(plant, name)) == 0
    } == {
        "meter1",
        "plc",
        "spare",
    }
    assert value(before, "modbus_link_up", link="bus1") == 0
    runner.run(30)
    after = metrics.text().decode()
    one_family_each(after)
    assert value(after, "modbus_up", **_labels(plant, "meter1")) == 1
    assert value(after, "modbus_up", **_labels(plant, "spare")) == 0
    assert value(after, "modbus_polls_total", device="plc") == 1
    assert value(after, "modbus_transactions_total", device="spare", outcome="timeout") == 1
    assert value(after, "modbus_link_up", link="bus1") == 1


def _reports_of(tmp_path, devices: int) -> tuple[list[int], object]:
    """One round of ``devices`` on one sim:// link, their reports going to the exporter's
    PlantMetrics: the bytecodes each device's report ran (the link thread's own, traced
    there), and the metrics."""
    from mbtool.cli.commands.exporter import PlantMetrics
    from mbtool.cli.program import register_schemes
    from mbtool.plant.inventory import load_inventory
    from mbtool.plant.schedule import Event, Plant

    register_schemes()
    path = tmp_path / f"plant-{devices}.toml"
    path.write_text(
        '[poll]\ninterval = 0.001\n[links.a]\ntarget = "sim://"\n'
        + "".join(f'[devices.d{n}]\nlink = "a"\nread = ["40001 1"]\n' for n in range(devices))
    )
    plant = load_inventory(str(path))
    metrics = PlantMetrics()
    counts: list[int] = []

    def counted(item) -> None:
        ran = [0]

        def trace(frame, event, arg):
            frame.f_trace_opcodes = True
            if event == "opcode":
                ran[0] += 1
            return trace

        sys.settrace(trace)
        try:
            metrics.report(item)
        finally:
            sys.settrace(None)
        if not isinstance(item, Event):
            counts.append(ran[0])

    runner = Plant(plant.links, plant.devices, counted, rounds=1)
    metrics.watch(runner)
    runner.run(60)
    return counts, metrics


def test_the_exporters_inventory_reports_a_poll_at_one_cost_however_many_devices_a_link_has(tmp_path):
    """Issue 40.18: after each poll the exporter added up every device of the link again for
    the link's totals: 459, 171, 58 polls a second for 10, 1,000, 3,000 devices where poll
    holds some 464.  The link's totals are kept as transactions end, so a device's report
    runs the same bytecodes on a link of 5 devices as on one of 400 (counted, not timed: a
    loaded machine moves a rate, not a count)."""
    few, _ = _reports_of(tmp_path, 5)
    many, metrics = _reports_of(tmp_path, 400)
    assert len(few) == 5 and len(many) == 400
    # the median: a link's first report also fills what is filled once
    few_ran, many_ran = sorted(few)[2], sorted(many)[200]
    assert many_ran <= 1.1 * few_ran, f"a report ran {many_ran} bytecodes on 400 devices, {few_ran} on 5"
    text = metrics.text().decode()
    devices = sum(
        number
        for (name, labels), number in samples(text).items()
        if name == "modbus_transactions_total" and dict(labels)["outcome"] == "answered"
    )
    assert value(text, "modbus_link_transactions_total", link="a", outcome="answered") == devices == 400


def _labels(plant, name: str) -> dict[str, str]:
    spec = next(device for device in plant.devices if device.name == name)
    return {"device": name, **(spec.tags or {})}


# --- the command line --------------------------------------------------------------------------


@pytest.mark.parametrize(
    "args, words",
    [
        ((), "nothing to export"),
        (("--maps", "{maps}"), "--maps reads maps from the targets --allow-target allows"),
        (("--maps", "{maps}", "--allow-target", "*", "--listen", "9502"), "--listen 9502: expected HOST:PORT"),
        (("--maps", "{maps}", "--allow-target", "*", "--listen", ":9502"), "--listen :9502: expected HOST:PORT"),
        (("--maps", "{maps}", "--allow-target", "*", "--listen", "::1:9502"), "goes in brackets"),
        (("--maps", "{maps}", "--allow-target", "*", "--listen", "127.0.0.1:70000"), "0..65535"),
        (("--maps", "{maps}/nosuch", "--allow-target", "*"), "--maps"),
        (("--maps", "{maps}", "--allow-target", "tcp://plc:99999"), "--allow-target tcp://plc:99999: bad port"),
        (("{clash}",), "point up: its metric, modbus_up, is one the exporter has of its own"),
        (("{stats_clash}",), "point transactions_total: its metric, modbus_transactions_total"),
        (("{bad}",), "unknown table [plant]"),
    ],
    ids=["nothing", "maps-alone", "no-host", "empty-host", "ipv6", "port", "no-folder", "bad-pattern", "clash",
         "stats-clash", "bad-inventory"],
)  # fmt: skip
def test_bad_options_or_inventory_are_exit_2_with_one_line_and_nothing_served(
    tmp_path, silent_server, args, words
):
    (tmp_path / "maps").mkdir()
    (tmp_path / "up.toml").write_text("[points.up]\nref = 40001\n")
    (tmp_path / "counter.toml").write_text("[points.transactions_total]\nref = 40001\n")
    for name, map_name in (("clash", "up.toml"), ("stats_clash", "counter.toml")):
        (tmp_path / f"{name}.toml").write_text(
            f'[links.a]\ntarget = "{silent_server.tcp_target}"\n[devices.d]\nlink = "a"\nmap = "{map_name}"\n'
        )
    (tmp_path / "bad.toml").write_text("[plant]\n")
    paths = {name: tmp_path / f"{name}.toml" for name in ("clash", "stats_clash", "bad")}
    argv = [arg.format(maps=tmp_path / "maps", **paths) for arg in args]
    line = assert_one_error_line(run_cli("exporter", *argv), 2)
    assert words in line, line
    assert silent_server.connections == 0


def test_a_port_already_taken_is_exit_6(tmp_path):
    taken = socket.socket()
    taken.bind(("127.0.0.1", 0))
    taken.listen(1)
    try:
        port = taken.getsockname()[1]
        res = run_cli("exporter", "--maps", tmp_path, "--allow-target", "*", "--listen", f"127.0.0.1:{port}")
        line = assert_one_error_line(res, 6)
        assert f"cannot listen on 127.0.0.1:{port}" in line
    finally:
        taken.close()


@pytest.mark.parametrize(
    "argv",
    [
        ["read", "-m", "examples/energy-meter.toml", "-p", "sim://", "-o", "prom"],
        ["poll", "examples/plant.toml", "--once", "-o", "prom"],
    ],
    ids=["read-m", "poll"],
)
def test_prometheus_client_is_loaded_by_the_exporter_alone(argv):
    """A one-shot read (and poll's Prometheus text) never pays for importing it."""
    code = (
        f"import sys; from mbtool.cli import main; sys.argv = ['mbtool', *{argv!r}]\n"
        "import atexit; atexit.register(lambda: print('LOADED' if 'prometheus_client' in sys.modules "
        "else 'NOT LOADED', file=sys.stderr))\n"
        "main()"
    )
    result = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=60, cwd=REPO_ROOT
    )
    assert "NOT LOADED" in result.stderr, result.stderr
    assert "modbus_" in result.stdout
