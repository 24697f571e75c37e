"""The TLS settings as profile keys and as poll's link keys, and poll over tls:// links
(issue 33): a certificate's path is read from the folder of the file that names it, as a
profile's map is; --insecure warns on every run that uses it, naming the link."""

from __future__ import annotations

import json
import shutil

import pytest
from helpers.checks import assert_one_error_line, expect_ok, plain_pairs
from helpers.devices import HOLDING, start_device
from helpers.run import run_cli

pytestmark = pytest.mark.timeout(90)


@pytest.fixture(scope="module")
def tls_device(pki):
    server = pki.server
    with start_device(
        tcp=True, framer="socket", units="1",
        tls=("--cert", str(server.cert), "--key", str(server.key), "--ca", str(pki.ca.cert)),
    ) as device:  # fmt: skip
        yield device


@pytest.fixture
def beside(tmp_path, pki):
    """A folder holding the operator's certificate, key and the CA, as a plant's config does."""
    for name, path in (("me.pem", pki.operator.cert), ("me.key", pki.operator.key), ("ca.pem", pki.ca.cert)):
        shutil.copy(path, tmp_path / name)
    return tmp_path


PROFILE = """
[profiles.plc]
port = "{target}"
cert = "me.pem"
key = "me.key"
ca = "ca.pem"
{more}
"""


def test_a_profile_carries_the_tls_settings_relative_to_its_file(
    beside, tls_device, monkeypatch, tmp_path_factory
):
    (beside / "config.toml").write_text(PROFILE.format(target=tls_device.target, more=""))
    elsewhere = tmp_path_factory.mktemp("cwd")
    monkeypatch.chdir(elsewhere)
    res = expect_ok(
        run_cli(
            "read-holding-registers",
            "0",
            "2",
            "-P",
            "plc",
            env={"MBTOOL_CONFIG": str(beside / "config.toml")},
        )
    )
    assert plain_pairs(res) == [(0, str(HOLDING[0])), (1, str(HOLDING[1]))]


def test_a_profiles_insecure_warns_and_its_server_name_is_taken(beside, tls_device):
    text = PROFILE.format(target=tls_device.target, more='server_name = "localhost"')
    (beside / "config.toml").write_text(text)
    expect_ok(
        run_cli(
            "read-holding-registers", "0", "-P", "plc", env={"MBTOOL_CONFIG": str(beside / "config.toml")}
        )
    )
    text = PROFILE.format(target=tls_device.target, more="insecure = true").replace('ca = "ca.pem"\n', "")
    (beside / "config.toml").write_text(text)
    res = expect_ok(
        run_cli(
            "read-holding-registers", "0", "-P", "plc", env={"MBTOOL_CONFIG": str(beside / "config.toml")}
        )
    )
    assert res.stderr.startswith(
        f"mbtool: warning: --insecure: the certificate of {tls_device.target} is not checked"
    )


@pytest.mark.parametrize(
    "line, words",
    [
        ("cert = 5", "profiles.plc.cert: a number, where cert takes"),
        ('insecure = "yes"', "profiles.plc.insecure: text, where insecure takes true or false"),
    ],
)
def test_a_profiles_tls_key_of_the_wrong_kind_is_exit_2(tmp_path, line, words):
    (tmp_path / "config.toml").write_text(f'[profiles.plc]\nport = "tls://127.0.0.1:1"\n{line}\n')
    res = run_cli(
        "read-holding-registers", "0", "-P", "plc", env={"MBTOOL_CONFIG": str(tmp_path / "config.toml")}
    )
    assert words in assert_one_error_line(res, 2)


INVENTORY = """
[links.secure]
target = "{target}"
cert = "me.pem"
key = "me.key"
{trust}

[devices.plc]
link = "secure"
unit = 1
read = ["40001 3"]
"""


def test_poll_takes_tls_links_with_their_files_beside_the_inventory(
    beside, tls_device, monkeypatch, tmp_path_factory
):
    (beside / "plant.toml").write_text(INVENTORY.format(target=tls_device.target, trust='ca = "ca.pem"'))
    monkeypatch.chdir(tmp_path_factory.mktemp("cwd"))
    res = expect_ok(run_cli("poll", str(beside / "plant.toml"), "--once", "-o", "json"))
    record = json.loads(res.stdout)
    assert [point["value"] for point in record["points"]] == HOLDING[:3]
    assert "warning" not in res.stderr


def test_poll_warns_of_an_insecure_link_by_name(beside, tls_device):
    (beside / "plant.toml").write_text(INVENTORY.format(target=tls_device.target, trust="insecure = true"))
    res = expect_ok(run_cli("poll", str(beside / "plant.toml"), "--once", "-o", "json"))
    assert res.stderr.splitlines()[0] == (
        f"mbtool: warning: --insecure: the certificate of {tls_device.target} (link secure) is not checked, "
        "so anyone on the way can read and change the traffic"
    )


def test_an_inventory_link_with_a_tls_key_off_tls_is_refused(tmp_path):
    (tmp_path / "plant.toml").write_text(
        '[links.bus]\ntarget = "tcp://127.0.0.1:1"\nca = "ca.pem"\n[devices.d]\nlink = "bus"\nread = ["40001"]\n'
    )
    res = run_cli("poll", str(tmp_path / "plant.toml"), "--once")
    line = assert_one_error_line(res, 2)
    assert line == (
        f"mbtool: {tmp_path / 'plant.toml'}: [links.bus]: --ca is for tls:// targets (Modbus/TCP Security); "
        "tcp://127.0.0.1:1 is not one"
    )


def test_an_inventory_links_certificate_is_read_before_anything_opens(beside, tls_device):
    (beside / "me.pem").unlink()
    (beside / "plant.toml").write_text(INVENTORY.format(target=tls_device.target, trust='ca = "ca.pem"'))
    res = run_cli("poll", str(beside / "plant.toml"), "--once")
    line = assert_one_error_line(res, 2)
    assert line == (
        f"mbtool: {beside / 'plant.toml'}: [links.secure]: cannot read --cert {beside / 'me.pem'}: "
        "No such file or directory"
    )
