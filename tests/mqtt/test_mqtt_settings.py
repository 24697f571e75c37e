"""The [mqtt] table as the plant's inventory (mbtool/plant/inventory.py, click-free) loads it."""

from __future__ import annotations

import pytest

from mbtool.errors import ExitCode, UsageError, exit_code_for
from mbtool.mqtt.settings import mqtt_settings
from mbtool.plant.inventory import load_inventory

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
        ('payload = "sparkplug_b"\ndiscovery = "homeassistant"\n', 'discovery and points = "point" go with'),
        ('primary_host = "scada"\n', 'primary_host: goes with payload = "sparkplug_b"'),
    ],
)
def test_a_sparkplug_setting_that_cannot_be_is_a_usage_error(tmp_path, table, message):
    path = tmp_path / "plant.toml"
    path.write_text(PLANT + '[mqtt]\nurl = "mqtt://b"\n' + table)
    with pytest.raises(UsageError) as error:
        load_inventory(str(path))
    assert message in str(error.value)
