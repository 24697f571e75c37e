"""poll publishing to a real MQTT broker (issue 42): Debian's mosquitto started on a free
loopback port (tests/peers/broker.py), read back by paho-mqtt subscribers; the devices are
``mbtool serve`` on pseudo-terminal buses and pymodbus's server over TCP.

serve's registers hold their own address (40011 holds 10) and 40101-40102 the float32 21.5;
pymodbus's device holds 100..119 from 40001.  Without mosquitto these tests skip, saying so.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import statistics
import subprocess
import tempfile
import time
from datetime import datetime
from pathlib import Path

import pytest
from helpers.devices import start_device
from helpers.mqtt import plant_on_broker, run_poll
from helpers.ptys import PTY_SERIAL_OPTS, PtyPair
from helpers.run import run_cli, run_mbtool, start_mbtool
from helpers.served import serve
from helpers.sockets import free_port
from peers.broker import Broker, Subscriber, mosquitto, needs_mosquitto

pytestmark = [pytest.mark.timeout(60), needs_mosquitto]

METER = """\
[points.level]
ref = 40011
scale = 0.1
unit = "m"

[points.flow]
ref = 40101
type = "float32"
unit = "m3/h"

[points.running]
ref = "00001"

[points.mode]
ref = 40003
enum = { 2 = "auto", 3 = "manual" }
"""


def _json(payloads: list[bytes]) -> list[dict]:
    return [json.loads(payload) for payload in payloads]


def test_a_plant_of_two_buses_and_a_tcp_device_publishes_every_point_of_every_poll(tmp_path):
    (tmp_path / "meter.toml").write_text(METER)
    bus_a, bus_b = PtyPair(), PtyPair()
    serial = ["--framer", "rtu", *PTY_SERIAL_OPTS]
    try:
        with (
            mosquitto() as broker,
            serve("-u", "1-2", *serial, target=bus_a.device_path),
            serve("-u", "5", *serial, target=bus_b.device_path),
            start_device(tcp=True, framer="socket", units="1") as tcp_device,
        ):
            plant = tmp_path / "plant.toml"
            plant.write_text(
                f'[poll]\ninterval = 0.2\n[links.a]\ntarget = "{bus_a.mbtool_path}"\nparity = "N"\n'
                f'[links.b]\ntarget = "{bus_b.mbtool_path}"\nparity = "N"\n'
                f'[links.tcp]\ntarget = "{tcp_device.target}"\n'
                '[devices.a1]\nlink = "a"\nunit = 1\nmap = "meter.toml"\ntags = { site = "north" }\n'
                '[devices.a2]\nlink = "a"\nunit = 2\nmap = "meter.toml"\ntags = { site = "north" }\n'
                '[devices.b5]\nlink = "b"\nunit = 5\nmap = "meter.toml"\ntags = { site = "south" }\n'
                '[devices.pm]\nlink = "tcp"\nunit = 1\nread = ["40001 2"]\ntags = { site = "east" }\n'
                '[mqtt]\ntopic = "plant/{site}/{device}"\nstatus_topic = "plant/poller"\n'
            )
            subscriber = Subscriber(broker.port, "plant/#")
            code, out, err = run_poll(plant, "--mqtt", broker.url, "--rounds", "3", "-o", "json")
            assert code == 0, err
            assert subscriber.wait_for(lambda messages: messages[-1][0] == "plant/poller", 5)
            subscriber.close()
    finally:
        bus_a.close()
        bus_b.close()
    expected = {"level": 1.0, "flow": 21.5, "running": True, "mode": "auto"}
    for topic, unit in (("plant/north/a1", 1), ("plant/north/a2", 2), ("plant/south/b5", 5)):
        records = _json(subscriber.on(topic))
        assert [record["points"] for record in records] == [expected] * 3, topic
        assert {record["unit"] for record in records} == {unit}
        assert all(record["time"].endswith("Z") for record in records)
    assert [r["points"] for r in _json(subscriber.on("plant/east/pm"))] == [{"40001": 100, "40002": 101}] * 3
    # What stdout says was read is what the broker carried, poll for poll.
    polled = [json.loads(line) for line in out.splitlines()]
    assert sum(len(r["points"]) for r in polled) == sum(
        len(r["points"]) for t in ("plant/north/a1", "plant/north/a2", "plant/south/b5", "plant/east/pm")
        for r in _json(subscriber.on(t))
    )  # fmt: skip
    for device in ("north/a1", "north/a2", "south/b5", "east/pm"):
        assert subscriber.on(f"plant/{device}/status") == [b"online"]
    assert subscriber.on("plant/poller") == [b"online", b"offline"]  # the birth, then a clean end
    assert "mqtt 127.0.0.1" in err  # the statistics name the broker


def test_on_change_publishes_a_steady_device_once_and_per_point_topics_carry_bare_values(tmp_path):
    (tmp_path / "meter.toml").write_text(METER)
    with mosquitto() as broker, serve("-u", "1") as device:
        plant = tmp_path / "plant.toml"
        plant.write_text(
            f'[poll]\ninterval = 0.1\n[links.l]\ntarget = "{device.target}"\n'
            '[devices.m]\nlink = "l"\nmap = "meter.toml"\n'
            '[mqtt]\non_change = true\npoints = "point"\ndeadband = "1%"\n'
        )
        subscriber = Subscriber(broker.port, "mbtool/#")
        code, _, err = run_poll(plant, "--mqtt", broker.url, "--rounds", "5")
        assert code == 0, err
        assert subscriber.wait_for(lambda messages: messages[-1][1] == b"offline", 5)
        subscriber.close()
    assert subscriber.on("mbtool/plant/m/level") == [b"1.0"]
    assert subscriber.on("mbtool/plant/m/flow") == [b"21.5"]
    assert subscriber.on("mbtool/plant/m/running") == [b"true"]
    assert subscriber.on("mbtool/plant/m/mode") == [b"auto"]
    assert "5 of" not in err and "published" in err


def test_a_device_killed_is_offline_on_its_status_topic_and_online_again_and_sigkill_leaves_the_will(
    tmp_path,
):
    inventory = (
        '[poll]\ninterval = 0.2\noffline_after = 1\nmax_backoff = 0.4\n[links.l]\ntarget = "{target}"\n'
        'timeout = 0.3\n[devices.pm]\nlink = "l"\nread = ["40001 1"]\n[mqtt]\nurl = "{url}"\n'
    )
    status = "mbtool/plant/pm/status"
    with plant_on_broker(tmp_path, inventory, "-o", "json", topics="mbtool/#") as plant:
        subscriber = plant.subscriber
        assert subscriber.wait_for(lambda m: (status, b"online", False) in m, 10)
        killed = time.monotonic()
        plant.kill_device()
        assert subscriber.wait_for(lambda m: subscriber.on(status)[-1:] == [b"offline"], 5)
        took = time.monotonic() - killed
        assert took < 4, f"offline {took:.1f} s after the device died"  # offline_after 1, a busy machine
        plant.device_back()
        assert subscriber.wait_for(lambda m: subscriber.on(status)[-1:] == [b"online"], 15)
        plant.poll.send_signal(signal.SIGKILL)  # no goodbye: the broker says the will
        plant.poll.wait(5)
        assert subscriber.wait_for(lambda m: subscriber.on("mbtool/plant/status")[-1:] == [b"offline"], 10)
        # The will is retained: a subscriber that comes later learns the poller is gone.
        late = Subscriber(plant.broker.port, "mbtool/plant/status")
        assert late.wait_for(lambda m: m == [("mbtool/plant/status", b"offline", True)], 5)
        late.close()
    out = plant.out
    assert subscriber.on(status) == [b"online", b"offline", b"online"]
    # Why, for a Node-RED flow that alerts: each change of state, as poll -o json's events say it.
    events = _json(subscriber.on("mbtool/plant/events"))
    printed = [record for record in map(json.loads, out.splitlines()) if "event" in record]
    assert [(e["event"], e.get("device")) for e in events] == [(e["event"], e.get("device")) for e in printed]
    assert [e["event"] for e in events if e.get("device") == "pm"] == ["offline", "online"]
    for sent, said in zip(events, printed, strict=True):
        assert sent.keys() == said.keys() and sent["reason" if "reason" in sent else "event"]
        assert sent["time"].endswith("Z") and sent["instance"] == os.uname().nodename


def test_a_bad_mqtt_table_is_one_line_and_exit_2_with_nothing_opened(tmp_path):
    for table, says in (
        ('url = "http://x"', "is not mqtt://"),
        ('url = "mqtt://h"\nqos = 2', "qos: expected a whole number, 0..1"),
        ('url = "mqtt://h"\ntopic = "a/{nope}/{device}"', "{nope} is not known"),
        ('url = "mqtt://h"\ntopic = "a/+/{device}"', "not a topic to publish on"),
        ('url = "mqtt://h"\ndeadband = "x%"', "not a percentage"),
        ('url = "mqtt://h"\nbogus = 1', "bogus: unknown key"),
        ('url = "mqtt://h"\nca = "ca.pem"', "mqtts:// settings"),
        # Sparkplug B fixes QoS and retain: the line of the key, and why
        ('url = "mqtt://h"\npayload = "sparkplug_b"\nretain = true', ":9: [mqtt] retain: not with payload"),
        ("qos = 1", "has no url"),
    ):
        plant = tmp_path / "plant.toml"
        plant.write_text(
            f'[links.l]\ntarget = "sim://"\n[devices.d]\nlink = "l"\nread = ["40001"]\n[mqtt]\n{table}\n'
        )
        res = run_cli("poll", str(plant), "--once")  # a usage error: no process of its own needed
        assert res.returncode == 2, (table, res.stderr)
        assert says in res.stderr and len(res.stderr.strip().splitlines()) == 1, (table, res.stderr)
    # --mqtt gives the url the table lacks; a broker that is not there holds nothing up.
    res = run_mbtool("poll", str(plant), "--once", "--mqtt", f"mqtt://127.0.0.1:{free_port()}")
    assert res.returncode == 0, res.stderr
    assert "unreachable (trying again): 0 published, 1 spooled (1 unsent)" in res.stderr


# --- Home Assistant discovery ------------------------------------------------------------------

# The fields Home Assistant's MQTT discovery documents for the components mbtool announces
# (https://www.home-assistant.io/integrations/sensor.mqtt/, binary_sensor.mqtt/, and the
# shared availability and device blocks); nothing else is allowed through.
SENSOR_CLASSES = [
    "apparent_power", "current", "duration", "energy", "enum", "frequency", "power", "pressure",
    "reactive_power", "temperature", "voltage", "volume", "volume_flow_rate",
]  # fmt: skip
COMMON = {
    "name": {"type": ["string", "null"]},
    "unique_id": {"type": "string", "pattern": "^[a-zA-Z0-9_-]+$"},
    "state_topic": {"type": "string", "pattern": "^[^+#]+$"},
    "value_template": {"type": "string"},
    "availability": {
        "type": "array",
        "minItems": 1,
        "items": {
            "type": "object",
            "required": ["topic"],
            "properties": {
                "topic": {"type": "string"},
                "payload_available": {"type": "string"},
                "payload_not_available": {"type": "string"},
                "value_template": {"type": "string"},
            },
            "additionalProperties": False,
        },
    },  # fmt: skip
    "availability_mode": {"enum": ["all", "any", "latest"]},
    "device": {
        "type": "object",
        "required": ["identifiers"],
        "properties": {
            "identifiers": {"type": "array", "items": {"type": "string"}, "minItems": 1},
            "name": {"type": "string"},
            "manufacturer": {"type": "string"},
            "model": {"type": "string"},
            "sw_version": {"type": "string"},
            "via_device": {"type": "string"},
        },  # fmt: skip
        "additionalProperties": False,
    },
}
SCHEMAS = {
    "sensor": {
        "type": "object",
        "required": ["state_topic", "unique_id", "device"],
        "properties": COMMON | {
            "device_class": {"enum": SENSOR_CLASSES},
            "state_class": {"enum": ["measurement", "total", "total_increasing"]},
            "unit_of_measurement": {"type": "string"},
            "options": {"type": "array", "items": {"type": "string"}, "minItems": 1},
        },
        "additionalProperties": False,
        # An enum sensor has options, and neither a unit nor a state class (HA refuses them).
        "if": {"properties": {"device_class": {"const": "enum"}}, "required": ["device_class"]},
        "then": {"required": ["options"], "not": {"anyOf": [{"required": ["state_class"]},
                                                          {"required": ["unit_of_measurement"]}]}},
        "else": {"not": {"required": ["options"]}},
    },  # fmt: skip
    "binary_sensor": {
        "type": "object",
        "required": ["state_topic", "unique_id", "device"],
        "properties": COMMON | {"payload_on": {"type": "string"}, "payload_off": {"type": "string"},
                                "device_class": {"type": "string"}},
        "additionalProperties": False,
    },
    # https://www.home-assistant.io/integrations/switch.mqtt/, select.mqtt/, number.mqtt/
    "switch": {
        "type": "object",
        "required": ["command_topic", "unique_id", "device"],
        "properties": COMMON | {"command_topic": {"type": "string", "pattern": "^[^+#]+$"},
                                "payload_on": {"type": "string"}, "payload_off": {"type": "string"}},
        "additionalProperties": False,
    },
    "select": {
        "type": "object",
        "required": ["command_topic", "options", "unique_id", "device"],
        "properties": COMMON | {"command_topic": {"type": "string", "pattern": "^[^+#]+$"},
                                "options": {"type": "array", "items": {"type": "string"}, "minItems": 1}},
        "additionalProperties": False,
    },
    "number": {
        "type": "object",
        "required": ["command_topic", "min", "max", "step", "unique_id", "device"],
        "properties": COMMON | {"command_topic": {"type": "string", "pattern": "^[^+#]+$"},
                                "min": {"type": "number"}, "max": {"type": "number"},
                                "step": {"type": "number", "minimum": 0.001},
                                "mode": {"enum": ["auto", "box", "slider"]},
                                "unit_of_measurement": {"type": "string"},
                                "device_class": {"enum": [c for c in SENSOR_CLASSES if c not in ("enum", "energy")]}},
        "additionalProperties": False,
    },
}  # fmt: skip


def test_home_assistant_discovery_configs_validate_and_name_the_right_component_for_each_point(tmp_path):
    jsonschema = pytest.importorskip("jsonschema")
    (tmp_path / "meter.toml").write_text(
        '[device]\nmanufacturer = "Acme"\nmodel = "M-1"\n'
        + METER
        + '[points.energy]\nref = 40021\nunit = "kWh"\n[points.tag]\nref = 40031\ntype = "string"\ncount = 2\n'
    )
    with mosquitto() as broker, serve("-u", "1") as device:
        plant = tmp_path / "plant.toml"
        plant.write_text(
            f'[links.l]\ntarget = "{device.target}"\n[devices.pump]\nlink = "l"\nmap = "meter.toml"\n'
            '[mqtt]\ndiscovery = "homeassistant"\n'
        )
        subscriber = Subscriber(broker.port, ["homeassistant/#", "mbtool/#"])
        code, _, err = run_poll(plant, "--mqtt", broker.url, "--once")
        assert code == 0, err
        assert subscriber.wait_for(lambda m: m and m[-1][1] == b"offline", 5)
        subscriber.close()
        # Retained: a Home Assistant started later still finds every entity.
        late = Subscriber(broker.port, "homeassistant/#")
        assert late.wait_for(lambda m: len(m) == 6 and all(retained for _, _, retained in m), 5)
        late.close()
    configs = {
        topic: json.loads(payload)
        for topic, payload, _ in subscriber.messages
        if topic.startswith("homeassistant/")
    }
    components = {}
    for topic, config in configs.items():
        prefix, component, node, object_id, last = topic.split("/")
        assert (prefix, last, node) == ("homeassistant", "config", "mbtool_plant_pump")
        jsonschema.validate(config, SCHEMAS[component])
        components[object_id] = component
        assert config["state_topic"] == "mbtool/plant/pump"
        assert [a["topic"] for a in config["availability"]] == [
            "mbtool/plant/status",
            "mbtool/plant/pump/status",
        ]
        assert config["device"] == {
            "identifiers": ["mbtool_plant_pump"], "name": "pump", "manufacturer": "Acme", "model": "M-1",
        }  # fmt: skip
    assert components == {
        "level": "sensor", "flow": "sensor", "running": "binary_sensor", "mode": "sensor", "energy": "sensor",
        "tag": "sensor",
    }  # fmt: skip
    by_name = {config["name"]: config for config in configs.values()}
    assert by_name["mode"]["options"] == ["auto", "manual"] and by_name["mode"]["device_class"] == "enum"
    assert (by_name["energy"]["device_class"], by_name["energy"]["state_class"]) == (
        "energy",
        "total_increasing",
    )
    assert by_name["flow"]["unit_of_measurement"] == "m³/h"
    assert by_name["flow"]["device_class"] == "volume_flow_rate"
    assert "unit_of_measurement" not in by_name["tag"] and "state_class" not in by_name["tag"]
    assert by_name["level"]["value_template"] == (
        '{% if "level" in value_json.points %}{{ value_json.points["level"] }}{% else %}{{ this.state }}{% endif %}'
    )


def test_with_writes_a_writable_point_is_a_switch_a_select_or_a_number_whose_command_is_its_set(tmp_path):
    jsonschema = pytest.importorskip("jsonschema")
    (tmp_path / "pump.toml").write_text(
        '[points.setpoint]\nref = 40501\nscale = 0.1\nunit = "m3/h"\naccess = "rw"\n'
        '[points.pump_on]\nref = "00001"\naccess = "rw"\n'
        '[points.mode]\nref = 40003\nenum = { 2 = "auto", 3 = "manual" }\naccess = "rw"\n'
        '[points.limit]\nref = 40502\ntype = "int16"\naccess = "rw"\n'
    )
    with mosquitto() as broker, serve("-u", "1") as device:
        plant = tmp_path / "plant.toml"
        plant.write_text(
            f'[links.l]\ntarget = "{device.target}"\n[devices.pump]\nlink = "l"\nmap = "pump.toml"\n'
            '[mqtt]\ndiscovery = "homeassistant"\nwrites = true\nallow = ["setpoint", "pump_on", "mode"]\n'
        )
        code, _, err = run_poll(plant, "--mqtt", broker.url, "--once")
        assert code == 0, err
        late = Subscriber(broker.port, "homeassistant/#")
        assert late.wait_for(lambda m: len(m) == 4, 5)
        late.close()
    configs = {
        topic.split("/")[3]: (topic.split("/")[1], json.loads(payload)) for topic, payload, _ in late.messages
    }
    for component, config in configs.values():
        jsonschema.validate(config, SCHEMAS[component])
    assert {name: component for name, (component, _) in configs.items()} == {
        "setpoint": "number", "pump_on": "switch", "mode": "select", "limit": "sensor",  # not on the allow-list
    }  # fmt: skip
    number = configs["setpoint"][1]
    assert (number["min"], number["max"], number["step"]) == (0, 6553.5, 0.1)
    assert number["command_topic"] == "mbtool/plant/pump/setpoint/set"
    assert configs["mode"][1]["options"] == ["auto", "manual"]


# --- the broker away ---------------------------------------------------------------------------

OUTAGE = 30.0  # seconds the broker is stopped (issue 42's Done when)
INTERVAL = 0.1


def _outage(tmp_path: Path, spool_sizes: dict[str, int]):
    """A poller an inventory of ``spool_sizes`` (its name: its spool's bound), each a device
    polled every 0.1 s, all at once; the broker stopped for OUTAGE seconds mid-run and started
    again on its port.  Each poller's (JSON lines, statistics, the messages a subscriber with a
    session on the broker received, its spool file after), and when the broker was stopped
    and started again (time.time())."""
    with tempfile.TemporaryDirectory(prefix="mbtool-broker-") as folder:
        broker = Broker(
            Path(folder), f"persistence true\npersistence_location {folder}/\nmax_queued_messages 100000\n"
        )
        broker.start()
        try:
            procs = {}
            subscriber = Subscriber(broker.port, [f"mbtool/{name}/m" for name in spool_sizes], session=True)
            for name, size in spool_sizes.items():
                plant = tmp_path / f"{name}.toml"
                plant.write_text(
                    f'[poll]\ninterval = {INTERVAL}\n[links.l]\ntarget = "sim://"\n'
                    '[devices.m]\nlink = "l"\nread = ["40001 1"]\n'
                    f'[mqtt]\nspool = "{name}.spool"\nspool_size = {size}\n'
                )
                # paho tries again 1, 3, 7, 15 and 31 s after the loss: back within 2 s of the broker.
                procs[name] = start_mbtool("poll", plant, "--mqtt", broker.url, "-o", "json", "--duration",
                                          str(2 + OUTAGE + 4), "--stats", "json")  # fmt: skip
            try:
                assert subscriber.wait_for(lambda m: len(m) >= 5 * len(procs), 10)
                broker.stop()
                stopped = time.time()
                time.sleep(OUTAGE)
                broker.start()
                restarted = time.time()
                ends = {name: proc.communicate(timeout=30) for name, proc in procs.items()}
            finally:
                for proc in procs.values():
                    proc.kill()
            for name, proc in procs.items():
                assert proc.returncode == 0, ends[name][1]
            assert subscriber.wait_for(lambda m: False, 1.5) is False  # what is owed has time to arrive
            subscriber.close()
        finally:
            broker.stop()
    runs = {}
    for name, (out, err) in ends.items():
        polls = [json.loads(line) for line in out.splitlines()]
        stats = json.loads(err.strip().splitlines()[-2])["mqtt"]
        received = _json(subscriber.on(f"mbtool/{name}/m"))
        runs[name] = (polls, stats, received, (tmp_path / f"{name}.spool").read_text())
    return runs, (stopped, restarted)


def _stamps(records: list[dict]) -> list[float]:
    return [round(datetime.fromisoformat(r["time"].replace("Z", "+00:00")).timestamp(), 3) for r in records]


def _received(records: list[dict]) -> list[float]:
    """The times of the messages received, in order, each once: QoS 1 is at least once, and
    the message the broker took as it stopped, before it could acknowledge it, comes again."""
    times = _stamps(records)
    assert times == sorted(times), "out of order"
    once = list(dict.fromkeys(times))
    assert len(times) - len(once) <= 2, f"{len(times) - len(once)} messages twice"
    return once


@pytest.mark.long  # started first (tests/conftest.py): it waits out the outage beside the others
@pytest.mark.timeout(100)
def test_the_broker_away_30_s_holds_no_poll_up_its_spool_delivers_in_order_and_counts_what_it_drops(
    tmp_path,
):
    """Issue 42's Done when: two pollers through one outage, one whose spool holds it all,
    one whose spool (50) it overflows."""
    runs, (stopped, restarted) = _outage(tmp_path, {"whole": 1000, "short": 50})
    for polls, _, _, _ in runs.values():
        # Polling's cadence while the broker was away is its cadence before: measured on the
        # time stamps of the polls stdout got.
        times = _stamps(polls)
        # The first gap is left out: the first poll goes when the link opens, off the grid.
        before = [b - a for a, b in zip(times[1:], times[2:], strict=False) if b < stopped]
        away = [b - a for a, b in zip(times, times[1:], strict=False) if stopped < a and b < restarted]
        assert len(away) >= OUTAGE / INTERVAL * 0.9, len(away)
        # The gaps away are those before (medians: a few polls before the stop, one late on a busy
        # machine would move a mean), and on average the interval asked: no poll was held up.
        assert statistics.median(away) == pytest.approx(statistics.median(before), abs=0.01), (before, away)
        assert statistics.mean(away) == pytest.approx(INTERVAL, abs=0.01), away
        # and none held up by the broker's absence (a reconnect in the way, a publish waiting):
        # ten intervals, more than a loaded machine delays one poll
        assert max(away) < 10 * INTERVAL, ("polling slowed while the broker was away", max(away))

    polls, stats, received, spool = runs["whole"]
    assert stats["dropped"] == 0 and stats["spool_dropped"] == 0, stats
    assert stats["spooled"] >= OUTAGE / INTERVAL * 0.9 and stats["in_spool"] == 0, stats
    # Every poll reached the subscriber, in order: those made while the broker was away from the spool.
    assert _received(received) == _stamps(polls)
    assert spool == ""  # sent, and emptied

    polls, stats, received, spool = runs["short"]
    assert stats["spooled"] >= OUTAGE / INTERVAL * 0.9, stats
    # Each message that came to the spool was sent from it or dropped, the newest 50 sent: the
    # drop count is exactly what the subscriber missed.
    assert stats["spool_dropped"] == stats["spooled"] - stats["spool_sent"] and stats["in_spool"] == 0
    assert 50 <= stats["spool_sent"] <= 52 and stats["dropped"] == 0, (
        stats
    )  # and any before the first connection
    sent, got = _stamps(polls), _received(received)
    assert len(got) == len(sent) - stats["spool_dropped"]
    # The ones missing are the oldest of the outage, in one run: the spool kept the newest 50.
    missing = [t for t in sent if t not in got]
    first = sent.index(missing[0])
    assert missing == sent[first : first + len(missing)]
    assert all(stopped - 1 < t < restarted for t in missing)
    assert spool == ""


# --- a broker that asks who we are ---------------------------------------------------------------


def test_a_password_and_mqtts_are_what_the_broker_asks_for_and_a_wrong_one_is_said(tmp_path, pki):
    folder = tmp_path / "broker"
    folder.mkdir()
    passwords = folder / "passwd"
    passwords.write_text("")
    subprocess.run(["mosquitto_passwd", "-b", str(passwords), "poller", "s3cret"], check=True, timeout=10)
    subprocess.run(["mosquitto_passwd", "-b", str(passwords), "reader", "r3ad"], check=True, timeout=10)
    tls_port = free_port()
    broker = Broker(
        folder,
        f"allow_anonymous false\npassword_file {passwords}\n"
        f"listener {tls_port} 127.0.0.1\ncafile {pki.ca.cert}\ncertfile {pki.server.cert}\nkeyfile {pki.server.key}\n",
    )
    broker.start()
    (tmp_path / "secret").write_text("s3cret\n")
    try:
        with serve("-u", "1") as device:
            subscriber = Subscriber(broker.port, "mbtool/#", username="reader", password="r3ad")
            for table, says in (
                # the password from a file, the broker's certificate checked against the CA
                (f'url = "mqtts://127.0.0.1:{tls_port}"\nusername = "poller"\npassword_file = "secret"\n'
                 f'ca = "{pki.ca.cert}"', "connected"),
                (f'url = "mqtt://127.0.0.1:{broker.port}"\nusername = "poller"\npassword = "wrong"',
                 "refused: Not authorized"),
                # a broker whose certificate no CA we trust signed
                (f'url = "mqtts://127.0.0.1:{tls_port}"\nusername = "poller"\npassword_file = "secret"\n'
                 f'ca = "{pki.other_ca.cert}"', "unreachable"),
            ):  # fmt: skip
                plant = tmp_path / "plant.toml"
                plant.write_text(
                    f'[poll]\ninterval = 0.2\n[links.l]\ntarget = "{device.target}"\n'
                    f'[devices.d]\nlink = "l"\nread = ["40001 1"]\n[mqtt]\n{table}\n'
                )
                code, _, err = run_poll(plant, "--rounds", "3")
                assert code == 0, err  # polling goes on whatever the broker says
                assert "mbtool: mqtt: broker 127.0.0.1:" in err and says in err, (table, err)
            # Only the run that was let in published its 3 polls.
            assert subscriber.wait_for(lambda m: len(subscriber.on("mbtool/plant/d")) == 3, 5)
            time.sleep(0.3)
            subscriber.close()
            assert len(subscriber.on("mbtool/plant/d")) == 3
    finally:
        broker.stop()


# --- writes from the broker ----------------------------------------------------------------------


def _requests(bus: PtyPair) -> list[tuple[str, bytes]]:
    """The frames that crossed an RTU bus, in order: (direction, bytes); mbtool's requests
    here are all 8 bytes (FC 01-04 reads, FC 06)."""
    frames, pending = [], b""
    for _, direction, data in list(bus.crossings):
        if direction == "request":
            pending += data
            while len(pending) >= 8:
                frames.append(("request", pending[:8]))
                pending = pending[8:]
        elif frames and frames[-1][0] == "reply":
            frames[-1] = ("reply", frames[-1][1] + data)
        else:
            frames.append(("reply", data))
    return frames


def test_a_set_publish_is_written_between_polls_read_back_and_a_bad_one_never_reaches_the_bus(tmp_path):
    (tmp_path / "pump.toml").write_text(
        "[points.level]\nref = 40011\nscale = 0.1\n"
        '[points.setpoint]\nref = 40501\nscale = 0.1\nunit = "m3/h"\naccess = "rw"\n'
        '[points.limit]\nref = 40502\naccess = "rw"\n'
    )
    bus = PtyPair()
    try:
        with (
            mosquitto() as broker,
            serve("-u", "1", "--framer", "rtu", *PTY_SERIAL_OPTS, target=bus.device_path),
        ):
            plant = tmp_path / "plant.toml"
            plant.write_text(
                f'[poll]\ninterval = 0.2\n[links.bus]\ntarget = "{bus.mbtool_path}"\nparity = "N"\n'
                '[devices.pump]\nlink = "bus"\nmap = "pump.toml"\n'
                f'[mqtt]\nurl = "{broker.url}"\nwrites = true\nallow = ["setpoint", "level"]\n'
            )
            subscriber = Subscriber(broker.port, "mbtool/#")
            proc = start_mbtool("poll", plant, "-o", "json", "--stats", "json")
            try:
                assert subscriber.wait_for(lambda m: subscriber.on("mbtool/plant/pump"), 10)
                base = "mbtool/plant/pump"
                for point, value, result in (
                    ("setpoint", "12.5", b"written"),
                    ("level", "3", b"refused: level (40011) is not writable: the map does not mark it rw"),
                    ("limit", "3", b"refused: limit is not on the allow-list (setpoint, level)"),
                    ("setpoint", "abc", b"refused: setpoint: abc is not a number"),
                    ("setpoint", "99999", b"refused: setpoint: 99999 m3/h (raw 999990) is out of range"),
                    ("nope", "1", b"refused: pump reads no point nope"),
                ):
                    subscriber.client.publish(f"{base}/{point}/set", value, qos=1)
                    topic = f"{base}/{point}/result"
                    count = len(subscriber.on(topic))
                    assert subscriber.wait_for(lambda m, t=topic, c=count: len(subscriber.on(t)) > c, 5), (
                        point
                    )
                    got = subscriber.on(topic)[-1]
                    assert got.startswith(result), (point, value, got)
                # The next poll reads what was written.
                assert subscriber.wait_for(
                    lambda m: json.loads(subscriber.on(base)[-1])["points"]["setpoint"] == 12.5, 5
                )
            finally:
                proc.send_signal(signal.SIGTERM)
                out, err = proc.communicate(timeout=10)
            subscriber.close()
    finally:
        bus.close()
    assert "mbtool: mqtt: write pump setpoint: written" in err
    stats = json.loads(err.strip().splitlines()[-2])["mqtt"]
    assert (stats["writes_received"], stats["writes_written"], stats["writes_refused"]) == (6, 1, 5)
    frames = _requests(bus)
    writes = [frame for direction, frame in frames if direction == "request" and frame[1] == 0x06]
    assert writes == [frames_06 := writes[0]] and frames_06[2:6] == bytes.fromhex("01F4 007D")  # 500 := 125
    # One request at a time on the bus: every reply answers the request just before it.
    for before, frame in zip(frames, frames[1:], strict=False):
        if frame[0] == "reply":
            assert before[0] == "request", "two replies in a row"
        else:
            assert before[0] == "reply", "a request sent before the last one was answered"


# --- issue 44: a fleet's labels, and two shards on one broker ----------------------------------


def test_two_shards_publish_their_halves_to_one_broker_labelled_and_never_collide(tmp_path):
    """Two ``poll --shard K/2`` of one inventory on one host: each its own client id (one
    broker session would throw the other off) and its own status topic, every device's
    messages once a poll, each carrying the fleet's site and instance."""
    plant = tmp_path / "plant.toml"
    links = [f"l{number}" for number in range(6)]  # l1, l4, l5: shard 0; l0, l2, l3: shard 1
    plant.write_text(
        '[poll]\ninterval = 0.1\nsite = "north"\ninstance = "edge7"\n'
        + "".join(f'[links.{link}]\ntarget = "sim://"\n' for link in links)
        + "".join(f'[devices.d{link[1]}]\nlink = "{link}"\nread = ["40001 2"]\n' for link in links)
        + '[mqtt]\ntopic = "plants/{site}/{instance}/{device}"\n'
    )
    with mosquitto() as broker:
        subscriber = Subscriber(broker.port, ["plants/#", "mbtool/#"])
        shards = [
            start_mbtool("poll", plant, "--shard", f"{k}/2", "--mqtt", broker.url, "--rounds", "8")
            for k in (0, 1)
        ]
        ends = [shard.communicate(timeout=20) for shard in shards]
        for shard, (_, err) in zip(shards, ends, strict=True):
            assert shard.returncode == 0 and "Traceback" not in err, err
            states = [line for line in err.splitlines() if line.startswith("mbtool: mqtt: broker")]
            assert not [line for line in states if " lost" in line], err  # no session thrown off by the other
        statuses = ("mbtool/plant/status/0of2", "mbtool/plant/status/1of2")
        assert subscriber.wait_for(lambda m: all(subscriber.on(s)[-1:] == [b"offline"] for s in statuses), 5)
        subscriber.close()
    for status in statuses:
        assert subscriber.on(status) == [b"online", b"offline"]
    for device in range(6):
        records = _json(subscriber.on(f"plants/north/edge7/d{device}"))
        assert len(records) == 8, device  # every poll once, by one shard
        assert all((r["site"], r["instance"]) == ("north", "edge7") for r in records)
        assert subscriber.on(f"plants/north/edge7/d{device}/status") == [b"online"]


# --- read --interval --mqtt: a one-liner on the broker ------------------------------------------


def test_read_interval_publishes_each_poll_as_one_message_with_its_availability(tmp_path):
    host = socket.gethostname()
    (tmp_path / "meter.toml").write_text(METER)
    with mosquitto() as broker, serve("-u", "1") as device:
        subscriber = Subscriber(broker.port, "mbtool/#")
        # A map's points by name, with the name given; stdout is as without --mqtt.
        proc = start_mbtool("read", "-m", str(tmp_path / "meter.toml"), "-p", device.target, "--interval", "0.1",
                     "--polls", "4", "-o", "json", "--mqtt", broker.url, "--name", "pump")  # fmt: skip
        out, err = proc.communicate(timeout=20)
        assert proc.returncode == 0 and "Traceback" not in err, err
        assert len(out.splitlines()) == 4
        # References, the device named by its unit; killed, the broker says the will.
        proc = start_mbtool("read", "40011", "2", "-u", "1", "-p", device.target, "--interval", "0.1",
                     "--mqtt", broker.url)  # fmt: skip
        try:
            assert subscriber.wait_for(lambda m: len(subscriber.on(f"mbtool/{host}/unit1")) >= 3, 10)
        finally:
            proc.kill()
            proc.communicate(timeout=5)
        assert subscriber.wait_for(
            lambda m: subscriber.on(f"mbtool/{host}/unit1/status")[-1:] == [b"offline"], 5
        )
        subscriber.close()
    records = _json(subscriber.on(f"mbtool/{host}/pump"))
    expected = {"level": 1.0, "flow": 21.5, "running": True, "mode": "auto"}
    assert [record["points"] for record in records] == [expected] * 4
    assert all(record["unit"] == 1 and record["instance"] == host for record in records)
    assert [r["time"] for r in records] == sorted(r["time"] for r in records)
    assert subscriber.on(f"mbtool/{host}/pump/status")[0] == b"online"
    assert subscriber.on(f"mbtool/{host}/pump/status")[-1] == b"offline"  # a clean end says so itself
    assert "mqtt 127.0.0.1" in err  # the broker's counts on stderr, as poll's statistics end
    assert {r["points"]["40011"] for r in _json(subscriber.on(f"mbtool/{host}/unit1"))} == {10}


def test_read_mqtt_without_polling_or_with_a_bad_name_is_one_line_and_exit_2():
    for args, says in (
        (["--mqtt", "mqtt://127.0.0.1:1"], "--mqtt publishes polls"),
        (["--mqtt", "mqtt://127.0.0.1:1", "--interval", "1", "--name", "a/b"], "--name 'a/b'"),
        (["--mqtt", "http://x", "--interval", "1"], "is not mqtt://"),
        (["--name", "pump", "--interval", "1"], "--name names the device on the broker: it goes with --mqtt"),
    ):
        res = run_cli("read", "40001", "-p", "tcp://127.0.0.1:1", *args)  # usage errors: in this process
        assert res.returncode == 2, (args, res.stderr)
        assert says in res.stderr and len(res.stderr.strip().splitlines()) == 1, (args, res.stderr)


def test_read_interval_says_its_device_offline_on_the_broker_while_its_polls_fail(tmp_path):
    host = socket.gethostname()
    with mosquitto() as broker:
        subscriber = Subscriber(broker.port, "mbtool/#")
        proc = start_mbtool("read", "40001", "-p", f"tcp://127.0.0.1:{free_port()}", "--timeout", "0.2",
                     "--interval", "0.2", "--mqtt", broker.url, "--name", "gone")  # fmt: skip
        try:
            status = f"mbtool/{host}/gone/status"
            assert subscriber.wait_for(lambda m: subscriber.on(status) == [b"online", b"offline"], 10)
            assert proc.poll() is None  # still polling: the device is offline, not the poller
        finally:
            proc.kill()
            proc.communicate(timeout=5)
        subscriber.close()
    assert subscriber.on(f"mbtool/{host}/gone") == []
