"""The [mqtt] table as the plant's inventory (mbtool/plant/inventory.py, click-free) loads it."""

from __future__ import annotations

import pytest

from mbtool.errors import ExitCode, UsageError, exit_code_for
from mbtool.mqtt.settings import mqtt_settings
from mbtool.mqtt.topics import Topics
from mbtool.plant.inventory import load_inventory, shard

PLANT = '[links.l]\ntarget = "tcp://127.0.0.1:1"\n[devices.pump]\nlink = "l"\nread = ["40001"]\n'


@pytest.mark.parametrize(
    ("table", "message"),
    [
        ("[mqtt]\nqos = 2\n", "[mqtt] qos: expected"),
        ('[mqtt]\nbroker = "x"\n', "[mqtt] broker: unknown key"),
        ('[mqtt]\nurl = "http://x"\n', "is not mqtt://"),
    ],
)
def test_a_mistake_in_the_mqtt_table_is_a_usage_error_of_the_inventory(tmp_path, table, message):
    """Issue 41.6's rule for every config mistake: UsageError (exit 2), naming file and key."""
    path = tmp_path / "plant.toml"
    path.write_text(PLANT + table)
    with pytest.raises(UsageError) as error:
        load_inventory(str(path))
    assert message in str(error.value) and str(path) in str(error.value)
    assert exit_code_for(error.value) == ExitCode.USAGE


def test_the_inventory_keeps_its_mqtt_table_for_poll(tmp_path):
    path = tmp_path / "plant.toml"
    path.write_text(PLANT + '[mqtt]\nurl = "mqtt://broker.example"\nqos = 0\n')
    assert load_inventory(str(path)).mqtt == {"url": "mqtt://broker.example", "qos": 0}


def test_sparkplug_b_names_the_group_after_the_devices_site_and_the_edge_node_after_the_inventory(tmp_path):
    path = tmp_path / "plant.toml"
    path.write_text(PLANT + 'tags = { site = "east" }\n[mqtt]\nurl = "mqtt://b"\npayload = "sparkplug_b"\n')
    plant = load_inventory(str(path))
    settings = mqtt_settings(plant.mqtt, str(path), plant.devices)
    assert (settings.sparkplug, settings.group, settings.edge_node) == (True, "east", "plant")


@pytest.mark.parametrize(
    ("table", "message"),
    [
        ('payload = "protobuf"\n', '[mqtt] payload: expected "json"'),
        ('payload = "sparkplug_b"\ngroup = "a/b"\n', "[mqtt] group: 'a/b': a Sparkplug id has no / + or #"),
        (
            'payload = "sparkplug_b"\ndiscovery = "homeassistant"\n',
            '[mqtt] discovery: not with payload = "sparkplug_b"',
        ),
        ('primary_host = "scada"\n', 'primary_host: goes with payload = "sparkplug_b"'),
    ],
)
def test_a_sparkplug_setting_that_cannot_be_is_a_usage_error(tmp_path, table, message):
    path = tmp_path / "plant.toml"
    path.write_text(PLANT + '[mqtt]\nurl = "mqtt://b"\n' + table)
    with pytest.raises(UsageError) as error:
        load_inventory(str(path))
    assert message in str(error.value)


# What plain JSON takes and Sparkplug B cannot honour: its topics are spBv1.0's, each
# message's QoS and retain flag are the spec's, and its data is never replayed from a spool.
@pytest.mark.parametrize(
    ("line", "why"),
    [
        ("qos = 1", "Sparkplug B fixes each message's QoS"),
        ("retain = true", "Sparkplug B retains none of an edge node's messages"),
        ('spool = "mqtt.spool"', "Sparkplug B's data is QoS 0"),
        ("spool_size = 10", "Sparkplug B's data is QoS 0"),
        ('topic = "plant/{device}"', "Sparkplug B's topics are spBv1.0/"),
        ('status_topic = "plant/poller"', "the edge node's NBIRTH and NDEATH are its status"),
        ('events_topic = "plant/events"', "the edge node's NBIRTH and NDEATH are its status"),
        ('points = "point"', "Sparkplug B carries a device's points as the metrics of one message"),
        ('discovery = "homeassistant"', "Home Assistant's discovery reads JSON topics"),
        ('discovery_prefix = "ha"', "Home Assistant's discovery reads JSON topics"),
    ],
)
def test_sparkplug_b_refuses_a_key_it_cannot_honour_naming_the_file_line_key_and_why(tmp_path, line, why):
    path = tmp_path / "plant.toml"
    text = PLANT + '[mqtt]\nurl = "mqtt://b"\npayload = "sparkplug_b"\non_change = true\n' + line + "\n"
    path.write_text(text)
    key = line.split(" ")[0]
    number = text.splitlines().index(line) + 1
    with pytest.raises(UsageError) as error:
        load_inventory(str(path))
    assert str(error.value).startswith(f"{path}:{number}: [mqtt] {key}: "), error.value
    assert why in str(error.value)
    # The same keys with plain JSON are taken.
    path.write_text(text.replace('payload = "sparkplug_b"\n', ""))
    load_inventory(str(path))


def test_sparkplug_b_honours_on_change_deadband_heartbeat_writes_and_the_ids(tmp_path):
    path = tmp_path / "plant.toml"
    path.write_text(
        PLANT + '[mqtt]\nurl = "mqtt://b"\npayload = "sparkplug_b"\non_change = true\ndeadband = 0.5\n'
        'heartbeat = 60\nwrites = true\ngroup = "g"\nedge_node = "n"\nkeepalive = 30\n'
    )
    plant = load_inventory(str(path))
    settings = mqtt_settings(plant.mqtt, str(path), plant.devices)
    assert (settings.on_change, settings.heartbeat, settings.group, settings.edge_node) == (
        True,
        60,
        "g",
        "n",
    )


# --- issue 44: the fleet's labels and shards on the broker ------------------------------------

FLEET = (
    '[poll]\nsite = "north"\ninstance = "edge7"\n'
    '[links.l0]\ntarget = "tcp://127.0.0.1:1"\n[links.l1]\ntarget = "tcp://127.0.0.1:2"\n'
    '[devices.pump]\nlink = "l0"\nread = ["40001"]\n[devices.fan]\nlink = "l1"\nread = ["40001"]\n'
)


def _settings(tmp_path, table: str, part: tuple[int, int] | None = None):
    path = tmp_path / "plant.toml"
    path.write_text(FLEET + '[mqtt]\nurl = "mqtt://b"\n' + table)
    plant = load_inventory(str(path))
    if part is not None:
        plant = shard(plant, *part)
    return mqtt_settings(plant.mqtt, str(path), plant.devices, labels=plant.labels, part=part)


def test_site_and_instance_fill_the_device_topics_and_the_poller_s_own(tmp_path):
    settings = _settings(
        tmp_path, 'topic = "plants/{site}/{instance}/{device}"\nstatus_topic = "plants/{site}/{instance}"\n'
    )
    topics = Topics(settings, settings_devices(tmp_path))
    assert topics.device == {"pump": "plants/north/edge7/pump", "fan": "plants/north/edge7/fan"}
    assert topics.status == "plants/north/edge7"
    assert settings.labels == {"site": "north", "instance": "edge7"}
    assert settings.client_id == "mbtool-edge7-plant"  # instance: the host name unless given


def settings_devices(tmp_path):
    return load_inventory(str(tmp_path / "plant.toml")).devices


def test_sparkplug_b_s_group_is_the_site_and_its_edge_node_the_inventory(tmp_path):
    settings = _settings(tmp_path, 'payload = "sparkplug_b"\n')
    assert (settings.group, settings.edge_node) == ("north", "plant")


def test_two_shards_of_one_inventory_are_two_clients_two_statuses_and_two_edge_nodes(tmp_path):
    ids = set()
    for part in ((0, 2), (1, 2)):
        json_ = _settings(tmp_path, "", part)
        sparkplug = _settings(tmp_path, 'payload = "sparkplug_b"\n', part)
        ids.add((json_.client_id, Topics(json_, []).status, sparkplug.client_id, sparkplug.edge_node))
    assert ids == {
        ("mbtool-edge7-plant-0of2", "mbtool/plant/status/0of2", "mbtool-edge7-plant-0of2", "plant-0of2"),
        ("mbtool-edge7-plant-1of2", "mbtool/plant/status/1of2", "mbtool-edge7-plant-1of2", "plant-1of2"),
    }


def test_a_template_naming_the_site_where_poll_gives_none_says_where_it_comes_from(tmp_path):
    path = tmp_path / "plant.toml"
    path.write_text(PLANT + '[mqtt]\nurl = "mqtt://b"\ntopic = "m/{site}/{device}"\n')
    with pytest.raises(UsageError) as error:
        load_inventory(str(path))
    assert '[poll] site = "..." gives {site}' in str(error.value)
