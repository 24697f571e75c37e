"""A map's [device] header (issue 43): manufacturer, model, kind, serial defaults, source and
the signature `mbtool identify` reads, checked when the map loads."""

from __future__ import annotations

import pytest

from mbtool.registermap.load import MapError, load_map

HEADER = """
[device]
order = "CDAB"
manufacturer = "Eastron"
model = "SDM630"
kind = "meter"
transport = "rtu"
firmware = "v2"
default_unit = 1
baud = 9600
parity = "none"
stopbits = 1
source = "Eastron SDM630 Modbus Protocol, V1.5, p. 3"

[[device.signature]]
ref = 30001
type = "float32"
within = [100, 300]

[[device.signature]]
ref = 464513
equals = 0x0070

[[device.signature]]
ref = 30003
refuses = true

[points.voltage_l1]
ref = 30001
type = "float32"
unit = "V"
"""


def write(tmp_path, text: str):
    path = tmp_path / "meter.toml"
    path.write_text(text)
    return path


def test_the_header_loads_with_the_map(tmp_path):
    header = load_map(write(tmp_path, HEADER)).header
    assert (header.manufacturer, header.model, header.kind, header.transport) == (
        "Eastron",
        "SDM630",
        "meter",
        "rtu",
    )
    assert header.serial() == {"baud": 9600, "parity": "N", "stopbits": 1}
    assert header.default_unit == 1
    assert header.source.startswith("Eastron SDM630")
    probes = header.signature
    assert [probe.describe() for probe in probes] == [
        "30001 float32 in 100..300",
        "464513 uint16 = 0x0070",
        "30003 refuses",
    ]
    # the probes read as the points do: [device]'s order applies
    assert probes[0].point.order == "CDAB"
    assert probes[0].judge(231.5, refused=False) and not probes[0].judge(1e-23, refused=False)
    assert probes[1].judge(0x70, refused=False) and not probes[1].judge(0x71, refused=False)
    assert probes[2].judge(None, refused=True) and not probes[2].judge(0, refused=False)


def test_a_map_without_a_header_has_none(tmp_path):
    assert load_map(write(tmp_path, "[points.a]\nref = 40001\n")).header is None


@pytest.mark.parametrize(
    "change, words",
    [
        (('kind = "meter"', 'kind = "toaster"'), "[device]: key kind: toaster is none of meter, inverter"),
        (("baud = 9600", "baud = 9601"), "[device]: key baud: 9601 is not a rate devices use"),
        (('parity = "none"', 'parity = "X"'), "[device]: key parity: X is none of"),
        (("stopbits = 1", "stopbits = 3"), "[device]: key stopbits: 3 is not a whole number in 1..2"),
        (("default_unit = 1", "default_unit = 256"), "key default_unit: 256 is not a whole number in 0..255"),
        (('source = "Eastron', 'sourc = "Eastron'), "[device]: unknown key sourc (known: type, order"),
        (("equals = 0x0070", 'equals = "SDM"'), "key signature 2: equals: 'SDM' is not a value a uint16"),
        (("within = [100, 300]", "within = [300, 100]"), "key signature 1: within = [LOW, HIGH]"),
        (("refuses = true", "refuses = true\nanswers = true"), "signature 3: give one expectation"),
        (("refuses = true", "refuses = true\nscale = 2"), "signature 3: unknown key scale"),
        (("ref = 30003", "ref = 3003"), "[device] signature 3: key ref:"),
        (
            ("within = [100, 300]", 'matches = "[0-9]+"'),
            "signature 1: matches is a regular expression for a string",
        ),
    ],
)
def test_a_wrong_header_key_is_one_line_naming_file_and_key(tmp_path, change, words):
    path = write(tmp_path, HEADER.replace(*change, 1))
    with pytest.raises(MapError) as caught:
        load_map(path)
    message = str(caught.value)
    assert message.startswith(f"{path}: ") and "\n" not in message
    assert words in message


def test_a_string_probe_matches_its_whole_text(tmp_path):
    text = HEADER.replace("within = [100, 300]", 'matches = "B2[134] .*"').replace(
        'type = "float32"\nmatches', 'type = "string"\ncount = 4\nmatches'
    )
    probe = load_map(write(tmp_path, text)).header.signature[0]
    assert probe.judge("B23 312", refused=False) and not probe.judge("xB23 312", refused=False)
