"""mbtool poll: a plant's devices on several buses and gateways, from one process (issue 31).

The plant of the end-to-end test is made of real peers the test starts: two serial buses
(pseudo-terminal pairs) with `mbtool serve -u 1-3` on one and pymodbus's RTU server on the
other, a TCP gateway (`mbtool bridge`) in front of a third bus, a pymodbus TCP device that is
stopped mid-run and started again, a unit that never answers and a link whose port does
not exist.  Outputs are read back with their own parsers.  The inventory's checks are
tests/cli/test_poll_inventory.py's, a device's state tests/plant/test_schedule.py's.
"""

from __future__ import annotations

import csv
import io
import json
import os
import re
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from helpers.checks import assert_one_error_line
from helpers.devices import HOLDING, start_device, stop_device
from helpers.prometheus import expositions, promtool_check
from helpers.ptys import PTY_SERIAL_OPTS, PtyPair
from helpers.run import REPO_ROOT, mbtool_env, run_cli, signals_as_from_a_shell, start_mbtool
from helpers.served import bridge, serve
from helpers.sockets import free_port


def write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


# --- the plant end to end --------------------------------------------------------------------

INTERVAL = 0.5


def _frames(crossings: list[tuple[float, str, bytes]]) -> list[tuple[str, int]]:
    """(direction, unit) of each frame on an RTU bus: a request of the plant is 8 bytes
    (FC 01-04 reads); a reply is the bytes up to the next request."""
    frames, request = [], b""
    for _, direction, data in crossings:
        if direction == "request":
            request += data
            while len(request) >= 8:
                frames.append(("request", request[0]))
                request = request[8:]
        elif not frames or frames[-1][0] == "request":
            frames.append(("reply", data[0]))
    return frames


def _one_at_a_time(bus: PtyPair) -> None:
    """No two requests on the bus at once: every reply answers the request just before it."""
    frames = _frames(bus.crossings)
    assert frames, "nothing crossed the bus"
    for before, frame in zip(frames, frames[1:], strict=False):
        if frame[0] == "reply":
            assert before == ("request", frame[1]), f"a reply from unit {frame[1]} after {before}"


def test_a_plant_of_buses_a_gateway_and_tcp_devices_polled_from_one_process(tmp_path):
    write(
        tmp_path / "meter.toml",
        '[points.flow]\nref = 40001\nunit = "m3/h"\n[points.level]\nref = 40002\nscale = 0.1\nunit = "m"\n',
    )
    port = free_port()
    bus_a, bus_gw = PtyPair(), PtyPair()
    device = None
    try:
        serial = ["--framer", "rtu", *PTY_SERIAL_OPTS]
        with (
            serve("-u", "1-3", *serial, target=bus_a.device_path),
            serve("-u", "1-2", *serial, target=bus_gw.device_path),
            bridge("-p", bus_gw.mbtool_path, *PTY_SERIAL_OPTS, "-t", "1", "-q") as gateway,
            start_device(tcp=False, framer="rtu", units="1,2") as bus_b,
        ):
            device = start_device(tcp=True, framer="socket", units="1", port=port)
            tcp_device = device.__enter__()
            plant = write(
                tmp_path / "plant.toml",
                f"""
[poll]
interval = {INTERVAL}
offline_after = 2
max_backoff = 2

[links.bus_a]
target = "{bus_a.mbtool_path}"
parity = "N"
timeout = 0.3

[links.bus_b]
target = "{bus_b.target}"
parity = "N"
timeout = 1

[links.gw]
target = "{gateway.target}"
timeout = 2

[links.tcp]
target = "{tcp_device.target}"
timeout = 0.5

[links.missing]
target = "/dev/ttyNOSUCH"

{"".join(f'[devices.a{u}]{chr(10)}link = "bus_a"{chr(10)}unit = {u}{chr(10)}map = "meter.toml"{chr(10)}tags = {{ bus = "a" }}{chr(10)}' for u in (1, 2, 3))}
[devices.ghost]
link = "bus_a"
unit = 9
read = ["40001 1"]

[devices.b1]
link = "bus_b"
unit = 1
read = ["40001 2"]

[devices.g1]
link = "gw"
unit = 1
read = ["40001 2"]

[devices.g2]
link = "gw"
unit = 2
map = "meter.toml"

[devices.pymodbus]
link = "tcp"
unit = 1
read = ["40001 2"]

[devices.far]
link = "missing"
unit = 1
read = ["40001 1"]
""",
            )
            proc = subprocess.Popen(
                [
                    sys.executable,
                    "-m",
                    "mbtool",
                    "poll",
                    str(plant),
                    "-o",
                    "json",
                    "--duration",
                    "9",
                    "--stats",
                    "json",
                ],
                cwd=REPO_ROOT,
                env=mbtool_env(),
                stdout=subprocess.PIPE,
                stderr=subprocess.PIPE,
                text=True,
            )
            time.sleep(2.5)
            stop_device(tcp_device.proc)  # killed mid-run ...
            time.sleep(2.5)
            device.__exit__(None, None, None)
            device = start_device(tcp=True, framer="socket", units="1", port=port)  # ... and back
            device.__enter__()
            out, err = proc.communicate(timeout=30)
    finally:
        if device is not None:
            device.__exit__(None, None, None)
        bus_a.close()
        bus_gw.close()
    assert proc.returncode == 8, err  # some devices answered, others did not
    records = [json.loads(line) for line in out.splitlines()]
    polls = [r for r in records if "event" not in r]
    events = [r for r in records if "event" in r]
    by_device: dict[str, list[dict]] = {}
    for record in polls:
        by_device.setdefault(record["device"], []).append(record)
    rounds = 9 / INTERVAL
    # Every live device, every round, with its values.
    for name in ("a1", "a2", "a3", "b1", "g1", "g2"):
        good = [r for r in by_device[name] if "points" in r]
        assert len(good) >= rounds - 3, (name, len(good), err)
        values = {p["name"]: p["value"] for p in good[-1]["points"]}
        if name in ("b1",):
            assert values == {"40001": HOLDING[0], "40002": HOLDING[1]}
        elif name == "g1":
            assert values == {"40001": 0, "40002": 1}
        else:
            assert values == {"flow": 0, "level": 0.1}
    assert by_device["a1"][0]["tags"] == {"bus": "a"}
    # The unit that never answers: offline after 2 polls, then tried once a back-off only.
    ghost = by_device["ghost"]
    assert {"event": "offline", "device": "ghost"}.items() <= next(
        e for e in events if e.get("device") == "ghost"
    ).items()
    assert len(ghost) <= 2 + 9 / 1.0, len(ghost)  # 2 polls, then 1 s and 2 s back-offs
    # The device killed mid-run went offline and came back.
    changes = [e["event"] for e in events if e.get("device") == "pymodbus"]
    assert changes == ["offline", "online"], (changes, err)
    assert "points" in by_device["pymodbus"][-1]
    # The link whose port does not exist: offline, its device too, and nothing else held up.
    assert any(e.get("link") == "missing" and e["event"] == "offline" for e in events)
    assert all("error" in r for r in by_device["far"])
    # One request at a time on every bus, the one behind the gateway too.
    _one_at_a_time(bus_a)
    _one_at_a_time(bus_b.pty)
    _one_at_a_time(bus_gw)
    stats = json.loads(err.strip().splitlines()[-2])
    assert stats["devices"]["ghost"]["timeout"] == stats["devices"]["ghost"]["transactions"] > 0
    assert stats["devices"]["a1"]["answered"] == stats["devices"]["a1"]["transactions"]
    assert stats["links"]["missing"]["open_failures"] >= 1


# --- outputs, read back with their own parsers ------------------------------------------------


@pytest.fixture
def small_plant(tmp_path):
    """Two mbtool serve devices over TCP, one with a map of a float and an enum; a dead unit."""
    meter = write(
        tmp_path / "meter.toml",
        '[points.voltage]\nref = 30001\ntype = "float32"\norder = "CDAB"\nunit = "V"\n'
        '[points.tariff]\nref = 40001\nenum = { 1 = "day", 2 = "night" }\n',
    )
    data = REPO_ROOT / "examples" / "energy-meter-data.toml"
    with serve("-u", "1-2", "--data", str(data)) as first, serve() as second:
        yield write(
            tmp_path / "plant.toml",
            f"""
[poll]
interval = 0.5
offline_after = 2

[links.gw]
target = "{first.target}"
timeout = 0.3

[links.plc]
target = "{second.target}"

[devices.meter1]
link = "gw"
unit = 1
map = "{meter.name}"
tags = {{ site = "north" }}

[devices.meter2]
link = "gw"
unit = 2
map = "{meter.name}"

[devices.dead]
link = "gw"
unit = 9
read = ["40001 1"]

[devices.plc]
link = "plc"
read = ["40001 2", "00001 2"]
""",
        )


def test_once_writes_json_lines_csv_influx_and_prom_each_readable_by_its_parser(small_plant):
    from line_protocol_parser import parse_line
    from prometheus_client.parser import text_string_to_metric_families

    res = run_cli("poll", small_plant, "--once", "-o", "json")
    assert res.returncode == 8, res  # the dead unit failed, the others answered
    records = {r["device"]: r for r in map(json.loads, res.stdout.splitlines()) if "event" not in r}
    assert records["meter1"]["points"] == [
        {"name": "voltage", "value": 230.1, "unit": "V", "ref": "30001"},
        {"name": "tariff", "value": "day", "ref": "40001"},  # no unit: no "unit" key beside the unit id
    ]
    assert not [p for p in records["plc"]["points"] if "unit" in p] and records["plc"]["unit"] == 1
    assert records["meter1"]["tags"] == {"site": "north"} and records["meter2"]["unit"] == 2
    assert "no response from unit 9" in records["dead"]["error"] and records["dead"]["exit_code"] == 3
    assert [p["value"] for p in records["plc"]["points"]] == [0, 1, True, False]

    rows = list(csv.DictReader(io.StringIO(run_cli("poll", small_plant, "--once", "-o", "csv").stdout)))
    assert {(r["device"], r["name"], r["value"], r["unit"], r["ref"]) for r in rows} >= {
        ("meter1", "voltage", "230.1", "V", "30001"),
        ("plc", "00001", "on", "", "00001"),
    }

    lines = run_cli("poll", small_plant, "--once", "-o", "influx").stdout.splitlines()
    points = {p["tags"]["device"]: p for p in map(parse_line, lines)}
    assert set(points) == {"meter1", "meter2", "plc"}  # the dead unit writes no line
    host = os.uname().nodename  # the instance label, as the inventory names none
    assert points["meter1"]["tags"] == {"device": "meter1", "site": "north", "unit": "1", "instance": host}
    assert points["meter1"]["fields"] == {"voltage": 230.1, "tariff": 1}

    text = run_cli("poll", small_plant, "--once", "-o", "prom").stdout
    samples = {
        (sample.name, tuple(sorted(sample.labels.items()))): sample.value
        for family in text_string_to_metric_families(text)
        for sample in family.samples
    }
    labels = (("device", "meter1"), ("instance", host), ("ref", "30001"), ("site", "north"))
    assert samples[("modbus_voltage", labels)] == 230.1


def _one_exposition(text: str) -> dict:
    """An exposition checked by promtool and prometheus_client's parser: each family once
    (a second HELP of one name is no exposition); its samples by (name, labels)."""
    from prometheus_client.parser import text_string_to_metric_families

    promtool_check(text)
    families = list(text_string_to_metric_families(text))
    names = [family.name for family in families]
    assert len(names) == len(set(names)), names
    return {
        (sample.name, tuple(sorted(sample.labels.items()))): sample.value
        for family in families
        for sample in family.samples
    }


def test_prom_once_is_one_exposition_and_rounds_a_stream_of_whole_ones(small_plant):
    """Cron writes `poll --once -o prom` into node_exporter's textfile folder: one exposition,
    each family once with its samples together, as promtool checks it; --rounds 2 writes
    whole expositions, one after another."""
    res = run_cli("poll", small_plant, "--once", "-o", "prom")
    assert res.returncode == 8, res
    samples = _one_exposition(res.stdout)
    ups = {dict(labels)["device"]: value for (name, labels), value in samples.items() if name == "modbus_up"}
    assert ups == {"meter1": 1, "meter2": 1, "plc": 1, "dead": 0}
    assert len(expositions(res.stdout)) == 1

    res = run_cli("poll", small_plant, "--rounds", "2", "-o", "prom")
    assert res.returncode == 8, res
    stream = expositions(res.stdout)
    assert len(stream) >= 2 and "".join(stream) == res.stdout
    for text in stream:
        labels = (("device", "meter2"), ("instance", os.uname().nodename), ("ref", "30001"))
        assert ("modbus_voltage", labels) in _one_exposition(text)


def test_raw_registers_are_one_family_as_read_writes_them_and_points_keep_their_names(small_plant, tmp_path):
    """read -o prom writes registers as modbus_value{table,address}: poll's -o prom and
    --textfile too, labelled by device, not a metric a register (modbus_40001)."""
    textfile = tmp_path / "plant.prom"
    res = run_cli("poll", small_plant, "--once", "-o", "prom", "--textfile", str(textfile))
    for text in (res.stdout, textfile.read_text()):
        samples = _one_exposition(text)
        plc = {
            (labels["table"], labels["address"], labels["ref"]): value
            for (name, pairs), value in samples.items()
            if name == "modbus_value" and (labels := dict(pairs))["device"] == "plc"
        }
        assert plc == {
            ("holding", "0", "40001"): 0,
            ("holding", "1", "40002"): 1,
            ("coils", "0", "00001"): 1,
            ("coils", "1", "00002"): 0,
        }
        names = {name for name, _ in samples}
        assert "modbus_voltage" in names and "modbus_tariff" in names  # a map's points by name
        assert not [name for name in names if name[len("modbus_") :][:1].isdigit()], names


def test_a_map_point_named_as_a_counter_is_warned_of_once_for_the_plant(tmp_path):
    """Two devices share a map whose point would be modbus_energy_total, a gauge: one warning
    naming the map, when the inventory is loaded for Prometheus; none for plain output."""
    write(tmp_path / "meter.toml", "[points.energy_total]\nref = 40001\n")
    with serve("-u", "1-2") as device:
        plant = write(
            tmp_path / "plant.toml",
            f'[links.a]\ntarget = "{device.target}"\n[devices.m1]\nlink = "a"\nunit = 1\nmap = "meter.toml"\n'
            '[devices.m2]\nlink = "a"\nunit = 2\nmap = "meter.toml"\n',
        )
        prom = run_cli("poll", plant, "--once", "-o", "prom")
        plain = run_cli("poll", plant, "--once", "-o", "plain")
    assert prom.returncode == 0 and plain.returncode == 0, (prom, plain)
    warnings = [line for line in prom.stderr.splitlines() if "warning" in line]
    assert len(warnings) == 1 and "meter.toml: point energy_total" in warnings[0], prom.stderr
    assert "modbus_energy_total, is a gauge" in warnings[0]
    assert "warning" not in plain.stderr


def test_a_refused_point_is_named_once_on_stderr_and_in_json(tmp_path, holed_device):
    """pymodbus's holed device refuses 40011 (exception 02): its line names the device and the
    point once (a point named by its reference, the reference once), and JSON's failed[].error
    is the device's answer alone, beside its own name and ref."""
    write(tmp_path / "holed.toml", "[points.flow]\nref = 40001\n[points.missing]\nref = 40011\n")
    plant = write(
        tmp_path / "plant.toml",
        f'[links.a]\ntarget = "{holed_device.target}"\n'
        '[devices.m]\nlink = "a"\nmap = "holed.toml"\n[devices.r]\nlink = "a"\nread = ["40010 2"]\n',
    )
    res = run_cli("poll", plant, "--once", "-o", "json")
    assert res.returncode == 8, res  # each device read in part
    refused = {
        line.split()[2]: line.split(" ", 3)[3] for line in res.stderr.splitlines() if "exception" in line
    }
    assert refused["m"].startswith("missing (40011): exception 02"), res.stderr
    assert refused["r"].startswith("40011: exception 02"), res.stderr
    assert all(text.count("40011") == 1 for text in refused.values()), refused
    records = {r["device"]: r for r in map(json.loads, res.stdout.splitlines()) if "device" in r}
    (failed,) = records["m"]["failed"]
    assert failed["name"] == "missing" and failed["ref"] == "40011"
    assert failed["error"].startswith("exception 02") and "40011" not in failed["error"], failed
    assert records["r"]["failed"][0]["error"] == failed["error"]


def test_influx_measurement_from_the_command_line_and_per_device(small_plant):
    """Telegraf users set the measurement per input: --measurement for the plant, and a
    device's own `measurement =` beats it."""
    from line_protocol_parser import parse_line

    text = small_plant.read_text().replace("unit = 2\n", 'unit = 2\nmeasurement = "meters"\n')
    small_plant.write_text(text)
    res = run_cli("poll", small_plant, "--once", "-o", "influx", "--measurement", "plant floor")
    assert res.returncode == 8, res
    measurements = {p["tags"]["device"]: p["measurement"] for p in map(parse_line, res.stdout.splitlines())}
    assert measurements == {"meter1": "plant floor", "meter2": "meters", "plc": "plant floor"}
    res = run_cli("poll", small_plant, "--once", "-o", "influx")
    assert {parse_line(line)["measurement"] for line in res.stdout.splitlines()} == {"modbus", "meters"}


def test_a_textfile_is_the_whole_plant_never_seen_half_written(small_plant, tmp_path):
    from prometheus_client.parser import text_string_to_metric_families

    textfile = tmp_path / "plant.prom"
    proc = start_mbtool(
        "poll",
        small_plant,
        "--textfile",
        textfile,
        "-o",
        "json",
        "--duration",
        "2",  # four rounds, each file read tens of thousands of times as it is replaced
        stdout=subprocess.DEVNULL,
    )
    reads, seen, stop = [], set(), threading.Event()

    def reader() -> None:
        while not stop.is_set():
            try:
                text = textfile.read_text()
            except FileNotFoundError:
                continue
            reads.append(text)
            for family in text_string_to_metric_families(text):  # a half file would not parse
                for sample in family.samples:
                    if sample.name == "modbus_up":
                        seen.add((sample.labels["device"], sample.value))

    thread = threading.Thread(target=reader)
    thread.start()
    try:
        proc.wait(timeout=30)
    finally:
        stop.set()
        thread.join(10)
    assert proc.returncode == 8, proc.stderr.read()
    assert len(reads) > 10
    assert ("dead", 0.0) in seen and ("meter1", 1.0) in seen and ("plc", 1.0) in seen
    final = textfile.read_text()
    assert (
        f'modbus_up{{device="dead",instance="{os.uname().nodename}"}} 0' in final
        and "modbus_voltage{" in final
    )
    assert not [name for name in os.listdir(tmp_path) if name.startswith(".plant.prom")]


def test_a_textfile_follows_the_fastest_device_not_the_slowest(tmp_path):
    """A device polled every 0.2 s beside one polled hourly: the textfile is rewritten every
    round of the fast one (not once an hour, serving its values as current meanwhile), each
    device with its own last success."""
    from prometheus_client.parser import text_string_to_metric_families

    textfile = tmp_path / "plant.prom"
    with serve("-u", "1-2") as device:
        plant = write(
            tmp_path / "plant.toml",
            f'[links.a]\ntarget = "{device.target}"\n'
            '[devices.fast]\nlink = "a"\nunit = 1\ninterval = 0.2\nread = ["40001 1"]\n'
            '[devices.slow]\nlink = "a"\nunit = 2\ninterval = 3600\nread = ["40001 1"]\n',
        )
        proc = start_mbtool(
            "poll", plant, "--textfile", textfile, "--duration", "2.5", stdout=subprocess.DEVNULL
        )
        seen: dict[str, set[float]] = {"fast": set(), "slow": set()}
        while proc.poll() is None:
            try:
                text = textfile.read_text()
            except FileNotFoundError:
                continue
            for family in text_string_to_metric_families(text):
                for sample in family.samples:
                    if sample.name == "modbus_last_success_timestamp_seconds":
                        seen[sample.labels["device"]].add(sample.value)
            time.sleep(0.02)
        assert proc.wait(timeout=10) == 0, proc.stderr.read()
    assert len(seen["fast"]) >= 5, seen  # about 12 rounds in 2.5 s
    assert len(seen["slow"]) == 1 and max(seen["slow"]) < max(seen["fast"]), seen


def test_a_value_the_map_calls_invalid_is_no_value_in_every_format(tmp_path):
    """A meter sends 0xFFFF before its sensor is ready: no value (JSON null, "invalid": true),
    never scaled into 6553.5, left out of influx and Prometheus; the other points as ever."""
    from line_protocol_parser import parse_line
    from prometheus_client.parser import text_string_to_metric_families

    data = write(tmp_path / "data.toml", "[holding_registers]\n0 = [0xFFFF, 230]\n")
    write(
        tmp_path / "meter.toml",
        '[device]\ninvalid = [0xFFFF]\n[points.power]\nref = 40001\nscale = 0.1\nunit = "kW"\n'
        '[points.voltage]\nref = 40002\nunit = "V"\n',
    )
    with serve("--data", str(data)) as device:
        plant = write(
            tmp_path / "plant.toml",
            f'[links.a]\ntarget = "{device.target}"\n[devices.m]\nlink = "a"\nmap = "meter.toml"\n',
        )
        run = {
            fmt: run_cli("poll", plant, "--once", "-o", fmt) for fmt in ("json", "plain", "influx", "prom")
        }
    assert all(res.returncode == 0 for res in run.values()), run
    (record,) = map(json.loads, run["json"].stdout.splitlines())
    assert record["points"][0] == {
        "name": "power",
        "value": None,
        "unit": "kW",
        "ref": "40001",
        "invalid": True,
    }
    assert record["points"][1]["value"] == 230
    assert [line.split(" ", 1)[1] for line in run["plain"].stdout.splitlines()] == [
        "m power invalid",
        "m voltage 230 V",
    ]
    assert parse_line(run["influx"].stdout)["fields"] == {"voltage": 230}
    names = {
        sample.name
        for family in text_string_to_metric_families(run["prom"].stdout)
        for sample in family.samples
    }
    assert "modbus_voltage" in names and "modbus_power" not in names


def _on_a_terminal(argv: list[str], seconds: float) -> tuple[int, str, str]:
    """Run mbtool with a pseudo-terminal as stdout for ``seconds``, then Ctrl-C: (status,
    what the terminal showed, stderr)."""
    import pty
    import select
    import signal

    master, slave = pty.openpty()
    proc = start_mbtool(*argv, env={"COLUMNS": "160"}, stdout=slave, text=False)
    os.close(slave)
    shown = b""
    try:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            if select.select([master], [], [], 0.1)[0]:
                try:
                    shown += os.read(master, 65536)
                except OSError:
                    break
        proc.send_signal(signal.SIGINT)
        end = time.monotonic() + 10
        while proc.poll() is None and time.monotonic() < end:
            if select.select([master], [], [], 0.1)[0]:
                try:
                    shown += os.read(master, 65536)
                except OSError:
                    break
        proc.wait(timeout=10)
        err = proc.stderr.read().decode()
    finally:
        os.close(master)
        proc.stderr.close()
    return proc.returncode, shown.decode(errors="replace"), err


def test_on_a_terminal_a_live_view_shows_each_device_and_the_statistics_follow(small_plant):
    code, shown, err = _on_a_terminal(["poll", str(small_plant)], 3)
    assert code == 8, err  # interrupted with the dead unit failing and the others answering
    for row in ("meter1", "meter2", "plc", "dead", "voltage=230.1", "tariff=day"):
        assert row in shown, shown[-2000:]
    assert "online" in shown and "offline" in shown
    assert "dead offline: " in shown, shown[-2000:]  # the event, as its line on stderr writes it
    # The statistics on stderr: a row a device and a link.
    table = err.splitlines()
    assert table[0].split()[:4] == ["name", "state", "polls", "trans"]
    rows = {line.split()[1]: line.split() for line in table[1:] if line.split()[:1] in (["device"], ["link"])}
    assert rows["dead"][2] == "offline" and rows["meter1"][2] == "online" and rows["gw"][0] == "link"
    assert "interrupted; 3 of 4 devices answered" in err.splitlines()[-1]


def test_the_statistics_table_has_a_column_for_every_outcome(tmp_path, raw_responder):
    """A device that hangs up on each request: its transactions are link_lost, in a column of
    their own, not transactions whose every outcome reads 0."""
    from helpers.sockets import CLOSE

    peer = raw_responder(lambda request: CLOSE)
    plant = write(
        tmp_path / "plant.toml",
        # the second round 0.5 s after the first (the 10 s interval left out only waited)
        f'[poll]\ninterval = 0.5\n[links.a]\ntarget = "{peer.tcp_target}"\ntimeout = 0.5\n'
        '[devices.d]\nlink = "a"\nread = ["40001 1"]\n',
    )
    res = run_cli("poll", plant, "--rounds", "2")
    assert res.returncode == 3, res  # no response: the peer closed the connection
    table = [line for line in res.stderr.splitlines() if not line.startswith("mbtool:")]
    head = table[0]
    for column in ("answered", "timeout", "corrupt", "not ours", "link lost", "exc"):
        assert column in head, head

    def cell(row: str, column: str) -> str:
        return row[head.index(column) :].split()[0]

    (device,) = [row for row in table if row.startswith("device")]
    assert cell(device, "trans") == "2" and cell(device, "link lost") == "2", table


def test_when_every_device_fails_the_status_is_the_failures_own(tmp_path, silent_server):
    plant = write(
        tmp_path / "plant.toml",
        f'[links.a]\ntarget = "{silent_server.socket_target.replace("socket", "tcp")}"\ntimeout = 0.2\n'
        '[devices.d]\nlink = "a"\nread = ["40001 1"]\n',
    )
    res = run_cli("poll", plant, "--once", "--stats", "json")
    assert res.returncode == 3, res  # no response
    stats = json.loads(res.stderr.splitlines()[-2])
    assert stats["devices"]["d"]["timeout"] == 1 and stats["devices"]["d"]["state"] == "unknown"
    assert res.stderr.splitlines()[-1].startswith("mbtool: 0 of 1 device answered: no response")


# --- runs that end: --once, --rounds, --duration ---------------------------------------------


def _records(res) -> tuple[list[dict], list[dict]]:
    """A -o json run's (poll records, event records)."""
    records = [json.loads(line) for line in res.stdout.splitlines()]
    return [r for r in records if "event" not in r], [r for r in records if "event" in r]


def test_a_run_that_ends_first_announces_no_next_try(tmp_path):
    """A link refused with --once, --rounds or --duration shorter than its back-off: no `next try
    in 10 s` nor `retry_in` for a try that never comes (issue 39.7)."""
    plant = write(
        tmp_path / "plant.toml",
        f'[poll]\ninterval = 5\n[links.gone]\ntarget = "tcp://127.0.0.1:{free_port()}"\n'
        '[devices.d]\nlink = "gone"\nread = ["40001"]\n',
    )
    for ending in (["--once"], ["--rounds", "3"], ["--duration", "1"]):
        res = run_cli("poll", plant, *ending, "-o", "json")
        assert res.returncode == 6, res
        polls, events = _records(res)
        assert {(e["event"], e.get("link", e.get("device"))) for e in events} == {
            ("offline", "gone"),
            ("offline", "d"),
        }
        assert all("retry_in" not in event for event in events), (ending, events)
        assert "next try" not in res.stderr and "Connection refused" in res.stderr, res.stderr
        assert len(polls) == 1, ending  # --rounds 3: nothing is tried again, so the run ends


def test_a_next_try_that_comes_within_the_run_is_announced_and_comes(tmp_path):
    plant = write(
        tmp_path / "plant.toml",
        f'[poll]\ninterval = 0.4\n[links.gone]\ntarget = "tcp://127.0.0.1:{free_port()}"\n'
        '[devices.d]\nlink = "gone"\nread = ["40001"]\n',
    )
    res = run_cli("poll", plant, "--duration", "2.5", "-o", "json")
    polls, events = _records(res)
    link = next(e for e in events if e.get("link") == "gone")
    assert link["retry_in"] == 0.8 and "next try in 0.8 s" in res.stderr
    assert len(polls) >= 2  # the try announced came


def test_rounds_counts_the_rounds_of_devices_that_answer_and_says_what_an_offline_one_got(tmp_path):
    """--rounds 4 on a link with a dead unit: the unit that answers is polled 4 times; the dead
    one, offline after one failure, is tried again only where its back-off ends within those
    rounds, every try it was promised comes, and the last line says how many it got
    (issue 39.8)."""
    with serve("-u", "1") as device:
        plant = write(
            tmp_path / "plant.toml",
            f'[poll]\ninterval = 0.3\noffline_after = 1\n[links.gw]\ntarget = "{device.target}"\n'
            'timeout = 0.1\n[devices.live]\nlink = "gw"\nread = ["40001"]\n'
            '[devices.dead]\nlink = "gw"\nunit = 9\nread = ["40001"]\n',
        )
        res = run_cli("poll", plant, "--rounds", "4", "-o", "json")
    assert res.returncode == 8, res
    polls, events = _records(res)
    assert [p["device"] for p in polls].count("live") == 4
    dead = [p["time"] for p in polls if p["device"] == "dead"]
    for event in events:
        if "retry_in" in event:  # the try it announces is made
            assert any(time > event["time"] for time in dead), (event, dead)
    assert 1 <= len(dead) < 4
    plural = "time" if len(dead) == 1 else "times"
    assert f"dead polled {len(dead)} {plural} of 4 (offline)" in res.stderr.splitlines()[-1], res.stderr


def test_a_finite_run_stopped_before_its_rounds_are_done_is_exit_130(tmp_path, silent_server):
    """SIGTERM to --once while a slow device is still being read and another waits its turn on
    that link: the round is not done, so not `1 of 3 devices answered` and a verdict, but 130
    (issue 40.14)."""
    import signal

    with serve() as device:
        plant = write(
            tmp_path / "plant.toml",
            f'[links.fast]\ntarget = "{device.target}"\n[links.slow]\ntarget = "{silent_server.tcp_target}"\n'
            'timeout = 1\n[devices.a]\nlink = "fast"\nread = ["40001"]\n'
            '[devices.b]\nlink = "slow"\nread = ["40001"]\n[devices.c]\nlink = "slow"\nunit = 2\nread = ["40001"]\n',
        )
        proc = start_mbtool("poll", plant, "--once", "-o", "json")
        try:
            assert json.loads(proc.stdout.readline())["device"] == "a"
            proc.send_signal(signal.SIGTERM)
            out, err = proc.communicate(timeout=10)
        finally:
            proc.kill()
    assert proc.returncode == 130, err
    assert err.splitlines()[-1].startswith("mbtool: interrupted"), err


def test_a_device_may_have_its_own_timeout_and_retries(tmp_path):
    """A slow meter on a fast bus (issue 39.24): its own timeout, 1 s, reads it where the link's
    0.15 s times out on its twin; its own retries try a dead unit three times a poll where the
    link's none try once; --stats shows what each device used."""
    # 0.5 s a reply: 0.35 s past the link's timeout, so that a client a loaded machine wakes
    # late from it does not find the twin's reply come meanwhile; 0.5 s inside the slow one's
    with serve("-u", "1-2", "--delay", "0.5") as device:
        plant = write(
            tmp_path / "plant.toml",
            f'[links.gw]\ntarget = "{device.target}"\ntimeout = 0.15\n'
            '[devices.slow]\nlink = "gw"\nread = ["40001"]\ntimeout = 1\n'
            '[devices.twin]\nlink = "gw"\nunit = 2\nread = ["40001"]\n'
            '[devices.dead]\nlink = "gw"\nunit = 9\nread = ["40001"]\nretries = 2\n',
        )
        res = run_cli("poll", plant, "--once", "-o", "json", "--stats", "json")
        table = run_cli("poll", plant, "--once", "-o", "json", "--hex").stderr
    assert res.returncode == 8, res
    polls, _ = _records(res)
    answered = {p["device"]: "points" in p for p in polls}
    assert answered == {"slow": True, "twin": False, "dead": False}
    stats = json.loads(res.stderr.splitlines()[-2])
    devices = stats["devices"]
    assert (devices["slow"]["timeout_seconds"], devices["slow"]["retries"]) == (1.0, 0)
    assert (devices["twin"]["timeout_seconds"], devices["twin"]["retries"]) == (0.15, 0)
    assert (devices["dead"]["timeout_seconds"], devices["dead"]["retries"]) == (0.15, 2)
    # The requests sent to each unit (MBAP: the unit is the 7th byte), whatever labels the trace.
    sent = [bytes.fromhex(m[1]) for m in re.finditer(r"TX ((?:[0-9A-F]{2} )*[0-9A-F]{2})", table)]
    assert [frame[6] for frame in sent].count(9) == 3 and [frame[6] for frame in sent].count(2) == 1, table
    assert (stats["links"]["gw"]["timeout_seconds"], stats["links"]["gw"]["retries"]) == (0.15, 0)
    rows = {line.split()[1]: line.split() for line in table.splitlines() if line.startswith("device")}
    head = next(line for line in table.splitlines() if line.split()[:2] == ["name", "state"]).split("  ")
    assert "timeout s" in [h.strip() for h in head] and rows["slow"][-2:] == ["1", "0"], table


def _address_space_capped() -> None:
    import resource

    signals_as_from_a_shell()
    resource.setrlimit(resource.RLIMIT_AS, (768 << 20, 768 << 20))  # a thread's stack is 8 MiB of it


def test_more_links_than_threads_the_system_allows_is_said_at_start(tmp_path):
    """A worker thread a link: under an address-space cap, 400 links cannot all have one. Said at
    start, exit 6 with the count, nothing polled (not `internal error: RuntimeError` mid-run,
    without statistics) (issue 40.17)."""
    links = 400
    plant = write(
        tmp_path / "plant.toml",
        "".join(
            f'[links.l{i}]\ntarget = "sim://"\n[devices.d{i}]\nlink = "l{i}"\nread = ["40001"]\n'
            for i in range(links)
        ),
    )
    res = subprocess.run(
        [sys.executable, "-m", "mbtool", "poll", str(plant), "--once", "-o", "json"],
        cwd=REPO_ROOT,
        env=mbtool_env(),
        preexec_fn=_address_space_capped,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert res.returncode == 6, res.stderr[-3000:]
    assert res.stdout == ""  # nothing was polled
    (line,) = res.stderr.splitlines()
    assert line.startswith("mbtool: ") and f"of {links} links" in line, line


def test_hex_labels_each_frame_with_its_link_and_device_and_can_trace_one_link(tmp_path):
    """--hex of a plant (issue 39.5): each trace line says whose frame it is, `[gw meter] TX …`,
    so MBAP frames of the gateway and RTU frames of the bus are told apart; --hex-link LINK
    traces that link alone (repeatable); a link the inventory lacks is exit 2."""
    with serve("-u", "1-2") as device:
        plant = write(
            tmp_path / "plant.toml",
            f'[links.gw]\ntarget = "{device.target}"\n[links.bus]\ntarget = "sim://"\n'
            '[devices.meter]\nlink = "gw"\nread = ["40001"]\n[devices.pump]\nlink = "gw"\nunit = 2\nread = ["40001"]\n'
            '[devices.plc]\nlink = "bus"\nread = ["40001 2"]\n',
        )
        every = run_cli("poll", plant, "--once", "--hex")
        one = run_cli("poll", plant, "--once", "--hex-link", "gw")
        unknown = run_cli("poll", plant, "--once", "--hex-link", "nosuch")
    assert every.returncode == 0 and one.returncode == 0, (every, one)
    trace = [line for line in every.stderr.splitlines() if " TX " in line or " RX " in line]
    labels = {line.split("] ")[0] + "]": line.split("] ")[1][:2] for line in trace}
    assert set(labels) == {"[gw meter]", "[gw pump]", "[bus plc]"}, every.stderr
    for line in trace:
        label, frame = line.split("] ", 1)
        unit = bytes.fromhex(frame[3:].split("  ")[0])[6 if label.startswith("[gw") else 0]
        assert unit == {"[gw meter": 1, "[gw pump": 2, "[bus plc": 1}[label], (
            line
        )  # MBAP's unit is its 7th byte
    traced = {line.split("] ")[0] + "]" for line in one.stderr.splitlines() if line.startswith("[")}
    assert traced == {"[gw meter]", "[gw pump]"}, one.stderr
    line = assert_one_error_line(unknown, 2)
    assert "nosuch" in line and "gw" in line and "bus" in line, line
