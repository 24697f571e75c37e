"""Patience for awkward devices (issue 18): each option against the `serve` fault that needs it."""

from __future__ import annotations

import re

import pytest
from helpers.run import run_cli
from helpers.served import serve

pytestmark = pytest.mark.timeout(60)


def polls(target: str, *options: str):
    return run_cli(
        "read-holding-registers",
        "0",
        "1",
        "--polls",
        "4",
        "--interval",
        "0",
        "-t",
        "0.3",
        *options,
        "-p",
        target,
    )


def test_pause_lets_a_device_that_drops_back_to_back_requests_answer_every_poll(tmp_path):
    with serve("--min-gap", "0.2") as server:
        target = f"tcp://{server.host}:{server.port}"
        res = polls(target)
        assert res.returncode == 3 and re.search(r"timeouts [1-9]", res.stderr)
        res = polls(target, "--pause", "0.25")
        assert res.returncode == 0 and "polls 4, replies 4, partial 0, timeouts 0" in res.stderr
        # A profile can say so for the device.
        config = tmp_path / "config.toml"
        config.write_text(f'[profiles.slow]\nport = "{target}"\npause = 0.25\n')
        res = run_cli(
            "read-holding-registers",
            "0",
            "1",
            "--polls",
            "3",
            "--interval",
            "0",
            "-t",
            "0.3",
            "-P",
            "slow",
            env={"MBTOOL_CONFIG": str(config)},
        )
        assert res.returncode == 0 and "replies 3, partial 0, timeouts 0" in res.stderr


def test_pause_spaces_the_requests_of_one_command(tmp_path):
    # A map read of two blocks is two requests: the second must wait too.
    path = tmp_path / "map.toml"
    path.write_text("[points.a]\nref = 40001\n[points.b]\nref = 40201\n")
    with serve("--min-gap", "0.2") as server:
        target = f"tcp://{server.host}:{server.port}"
        assert run_cli("read", "-m", path, "-t", "0.3", "-p", target).returncode == 3
        res = run_cli("read", "-m", path, "-t", "0.3", "--pause", "0.25", "-p", target)
        assert res.returncode == 0 and res.stdout.splitlines() == [
            "a 0",
            "b 3",
        ]  # sim data: the FIFO count at 200


def test_connect_delay_waits_out_a_device_that_drops_the_first_request():
    with serve("--settle", "0.3") as server:
        target = f"tcp://{server.host}:{server.port}"
        res = run_cli("read-holding-registers", "0", "1", "-t", "0.2", "-p", target)
        assert res.returncode == 3
        res = run_cli("read-holding-registers", "0", "1", "-t", "0.2", "--connect-delay", "0.4", "-p", target)
        assert res.returncode == 0 and res.stdout.splitlines() == ["0 0"]


def test_reconnect_each_gets_past_a_gateway_that_leaks_connections():
    with serve("--connection-requests", "1") as server:
        target = f"tcp://{server.host}:{server.port}"
        res = polls(target)
        assert res.returncode == 3 and "replies 1, partial 0, timeouts 3" in res.stderr
        res = polls(target, "--reconnect-each")
        assert res.returncode == 0 and "polls 4, replies 4, partial 0, timeouts 0" in res.stderr


def test_the_faults_are_for_tcp_clients():
    res = run_cli("serve", "-p", "/dev/null", "--min-gap", "1")
    assert res.returncode == 2 and "faults of TCP clients" in res.stderr


@pytest.mark.parametrize(
    "fault, deviation",
    [
        (("--pad", "2"), "2 bytes after a complete reply, ignored"),
        (("--byte-count-off", "1"), "byte count 5, but the data is the 4 bytes asked for"),
        (("--reply-unit", "9"), "reply from unit 9, expected unit 1"),
    ],
)
def test_lenient_accepts_a_harmless_deviation_with_one_warning(fault, deviation):
    with serve(*fault) as server:
        target = f"tcp://{server.host}:{server.port}"
        res = run_cli("read-holding-registers", "0", "2", "-t", "0.3", "-p", target)
        assert res.returncode == 5 and "--lenient" in res.stderr and res.stdout == ""
        res = run_cli("read-holding-registers", "0", "2", "-t", "0.3", "--lenient", "-p", target)
        assert res.returncode == 0 and res.stdout.splitlines() == ["0 0", "1 1"]
        assert res.stderr == f"mbtool: warning: {deviation} (accepted: --lenient)\n"


def test_lenient_does_not_guess_at_an_ambiguous_reply():
    # A byte count one too high and one byte of padding: the byte count covers the padding,
    # the data is no longer what was asked for, and nothing says which byte is extra.
    with serve("--byte-count-off", "1", "--pad", "1") as server:
        target = f"tcp://{server.host}:{server.port}"
        res = run_cli("read-holding-registers", "0", "2", "--lenient", "-t", "0.3", "-p", target)
        assert res.returncode == 5 and res.stdout == "" and "warning" not in res.stderr


def test_lenient_polling_names_what_it_accepted_in_the_summary():
    with serve("--pad", "2") as server:
        target = f"tcp://{server.host}:{server.port}"
        res = polls(target, "--lenient")
        assert res.returncode == 0 and "replies 4" in res.stderr
        assert "accepted (--lenient): 2 bytes after a complete reply, ignored" in res.stderr.splitlines()[-1]
