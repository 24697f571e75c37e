"""What the options say holds for their own run only (issue 30): two commands run in one
process, each does what its own options say, whatever the one before it said.

The runs go through click's CliRunner against the command group, in one process, as a
program embedding mbtool's commands (or a test) runs them.
"""

from __future__ import annotations

import pytest
from click.testing import CliRunner
from line_protocol_parser import parse_line
from prometheus_client.parser import text_string_to_metric_families

from mbtool.cli.program import cli

pytestmark = pytest.mark.timeout(60)


def invoke(*args, env: dict | None = None):
    return CliRunner().invoke(cli, [str(arg) for arg in args], env=env)


def families(text: str) -> dict:
    return {family.name: family for family in text_string_to_metric_families(text)}


def test_a_textfile_run_leaves_the_next_prom_run_writing_to_stdout(tcp_device, tmp_path):
    """After --textfile F, -o prom prints its exposition and leaves F alone."""
    path = tmp_path / "modbus.prom"
    first = invoke("read-holding-registers", "0", "2", "--textfile", path, "-p", tcp_device.target)
    assert first.exit_code == 0, first.output
    assert first.stdout == "" and "modbus_value" in families(path.read_text())
    path.write_text("left alone\n")
    second = invoke("read-holding-registers", "0", "2", "-o", "prom", "-p", tcp_device.target)
    assert second.exit_code == 0, second.output
    assert len(families(second.stdout)["modbus_value"].samples) == 2
    assert path.read_text() == "left alone\n"


def test_no_header_is_its_own_runs_only(tcp_device):
    first = invoke("read-holding-registers", "0", "2", "-o", "csv", "--no-header", "-p", tcp_device.target)
    assert first.exit_code == 0 and first.stdout.splitlines()[0].startswith("0,"), first.output
    second = invoke("read-holding-registers", "0", "2", "-o", "csv", "-p", tcp_device.target)
    assert second.exit_code == 0 and second.stdout.splitlines()[0] == "address,value", second.output


def test_a_profiles_name_labels_its_own_runs_metrics_only(tcp_device, tmp_path):
    """-P names the device in the labels of its run; a run without it has no device label."""
    config = tmp_path / "config.toml"
    config.write_text(f'[profiles.plant]\nport = "{tcp_device.target}"\n')
    env = {"MBTOOL_CONFIG": str(config)}
    first = invoke("read-holding-registers", "0", "1", "-o", "prom", "-P", "plant", env=env)
    assert first.exit_code == 0, first.output
    assert families(first.stdout)["modbus_value"].samples[0].labels["device"] == "plant"
    path = tmp_path / "modbus.prom"
    second = invoke("read-holding-registers", "0", "1", "--textfile", path, "-p", tcp_device.target, env=env)
    assert second.exit_code == 0, second.output
    for family in families(path.read_text()).values():
        assert all("device" not in sample.labels for sample in family.samples), family


def test_a_run_tells_of_its_own_last_success_only(tcp_device, silent_server):
    """-o prom on stdout knows of no success before its own run: the run before it in the
    same process read the device, this one could not."""
    first = invoke("read-holding-registers", "0", "1", "-o", "prom", "-p", tcp_device.target)
    assert first.exit_code == 0, first.output
    second = invoke(
        "read-holding-registers", "0", "1", "-o", "prom", "-t", "0.2", "-p", silent_server.tcp_target
    )
    assert second.exit_code != 0
    found = families(second.stdout)
    assert set(found) == {"modbus_up"} and found["modbus_up"].samples[0].value == 0


def test_each_run_warns_of_the_values_it_leaves_out(not_finite):
    """The InfluxDB line's warning for a NaN is once a run, not once a process."""
    for run in range(2):
        res = invoke("read", "40001", "4", "--type", "float32", "-o", "influx", "-p", not_finite.target)
        assert res.exit_code == 0, res.output
        assert parse_line(res.stdout.strip())["fields"] == {"40007": 21.5}
        assert "mbtool: warning: holding 40001 reads nan" in res.stderr, f"run {run + 1}"
