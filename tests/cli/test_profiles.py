"""Profiles (-P/--profile): precedence option > environment > profile > default, and bad files."""

from __future__ import annotations

from helpers.checks import assert_one_error_line, expect_ok, plain_pairs
from helpers.run import run_cli


def config(tmp_path, text: str) -> dict[str, str]:
    path = tmp_path / "config.toml"
    path.write_text(text)
    return {"MBTOOL_CONFIG": str(path)}


PROFILES = """
[profiles.dev]
port = "sim://"
unit = 2
timeout = 0.3
retries = 0
echo = false
parity = "n"
bytesize = 8
stopbits = 1
baud = 9600
framer = "rtu"

[profiles.tcp]
port = "{target}"
unit = 1
"""


def test_profile_supplies_port_and_unit(tmp_path, tcp_device):
    env = config(tmp_path, PROFILES.format(target=tcp_device.target))
    res = expect_ok(run_cli("read-holding-registers", "0", "2", "-P", "tcp", env=env))
    assert [a for a, _ in plain_pairs(res)] == [0, 1]


def test_profile_beats_default(tmp_path):
    # unit 2 from the profile: sim:// is unit 1 only, so the read times out (after the profile's 0.3 s)
    env = config(tmp_path, PROFILES.format(target="x"))
    res = run_cli("read-holding-registers", "0", "1", "--profile", "dev", env=env)
    line = assert_one_error_line(res, 3)
    assert "unit 2" in line and "0.3 s" in line


def test_environment_beats_profile(tmp_path):
    env = config(tmp_path, PROFILES.format(target="x")) | {"MBTOOL_UNIT": "1"}
    expect_ok(run_cli("read-holding-registers", "0", "1", "-P", "dev", env=env))
    env |= {"MBTOOL_PORT": "tcp://127.0.0.1:1"}
    res = run_cli("read-holding-registers", "0", "1", "-P", "dev", env=env)
    assert_one_error_line(res, 6)


def test_option_beats_environment_and_profile(tmp_path):
    env = config(tmp_path, PROFILES.format(target="x")) | {"MBTOOL_UNIT": "3"}
    expect_ok(run_cli("read-holding-registers", "0", "1", "-P", "dev", "-u", "1", env=env))
    res = run_cli(
        "read-holding-registers", "0", "1", "-P", "dev", "-u", "1", "-p", "tcp://127.0.0.1:1", env=env
    )
    assert_one_error_line(res, 6)


def test_profile_on_other_device_commands(tmp_path):
    env = config(tmp_path, '[profiles.s]\nport = "sim://"\n')
    expect_ok(run_cli("write-register", "5", "7", "-P", "s", env=env))
    expect_ok(run_cli("read-exception-status", "-P", "s", env=env))


def test_xdg_config_home(tmp_path):
    (tmp_path / "mbtool").mkdir()
    (tmp_path / "mbtool" / "config.toml").write_text('[profiles.s]\nport = "sim://"\n')
    expect_ok(run_cli("read-coils", "0", "1", "-P", "s", env={"XDG_CONFIG_HOME": str(tmp_path)}))


def test_unknown_profile(tmp_path):
    env = config(tmp_path, PROFILES.format(target="x"))
    line = assert_one_error_line(run_cli("read-coils", "0", "1", "-P", "nope", env=env), 2)
    assert env["MBTOOL_CONFIG"] in line and "no profile nope" in line and "dev, tcp" in line


def test_unknown_key(tmp_path):
    env = config(tmp_path, '[profiles.s]\nport = "sim://"\nspeed = 9600\n')
    line = assert_one_error_line(run_cli("read-coils", "0", "1", "-P", "s", env=env), 2)
    assert env["MBTOOL_CONFIG"] in line and "profiles.s.speed" in line and "unknown key" in line


def test_bad_values(tmp_path):
    for key, value in [
        ("unit", "300"),
        ("baud", "0"),
        ("parity", '"X"'),
        ("timeout", "0"),
        ("echo", '"yes"'),
        ("unit", "1.5"),
        ("framer", '"udp"'),
        ("port", "[1]"),
        ("port", "5"),  # a number is no device path (issue 13.6)
        ("unit", "true"),
        ("unit", '"2"'),
        ("baud", '"9600"'),
        ("timeout", '"1"'),
        ("rs485", "1"),
    ]:
        port = "" if key == "port" else 'port = "sim://"\n'
        env = config(tmp_path, f"[profiles.s]\n{port}{key} = {value}\n")
        res = run_cli("read-coils", "0", "1", "-P", "s", env=env)
        line = assert_one_error_line(res, 2)
        assert env["MBTOOL_CONFIG"] in line and f"profiles.s.{key}" in line, line


def test_unreadable_or_broken_file(tmp_path):
    missing = str(tmp_path / "missing.toml")
    line = assert_one_error_line(
        run_cli("read-coils", "0", "1", "-P", "s", env={"MBTOOL_CONFIG": missing}), 2
    )
    assert missing in line
    env = config(tmp_path, "[profiles.s\nport = 1\n")
    line = assert_one_error_line(run_cli("read-coils", "0", "1", "-P", "s", env=env), 2)
    assert env["MBTOOL_CONFIG"] in line and "TOML" in line


def test_a_number_for_the_port_says_it_wants_text(tmp_path):
    env = config(tmp_path, "[profiles.s]\nport = 5\n")
    line = assert_one_error_line(run_cli("read-coils", "0", "1", "-P", "s", env=env), 2)
    assert line.endswith(
        'profiles.s.port: a number, where port takes text, such as "/dev/ttyUSB0" or "tcp://10.0.0.5"'
    )


def test_keys_a_command_has_no_option_for_are_checked_too(tmp_path):
    """monitor has no --unit, but a bad unit is still a bad file."""
    env = config(tmp_path, '[profiles.s]\nport = "sim://"\nunit = "x"\n')
    line = assert_one_error_line(run_cli("monitor", "--from-file", "/dev/null", "-P", "s", env=env), 2)
    assert "profiles.s.unit" in line


def test_a_file_that_is_not_utf8_is_named(tmp_path):
    path = tmp_path / "config.toml"
    path.write_bytes(b'[profiles.s]\nport = "/dev/tty\xe9"\n')
    line = assert_one_error_line(
        run_cli("read-coils", "0", "1", "-P", "s", env={"MBTOOL_CONFIG": str(path)}), 2
    )
    assert line == f"mbtool: {path}: not UTF-8 text (byte 29), as TOML must be"


def test_no_profile_no_config_needed(tmp_path):
    # Without -P the file is never read: a broken one does not matter.
    env = config(tmp_path, "not toml [")
    expect_ok(run_cli("read-coils", "0", "1", "-p", "sim://", env=env))
