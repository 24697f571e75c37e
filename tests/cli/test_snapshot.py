"""Snapshots of a device as files (issue 16): diff of two dumps, restore's fewest writes, and a
dump that cannot be written, in-process where no process of its own is needed."""

from __future__ import annotations

import resource
import subprocess
import sys
import tomllib

from helpers.checks import assert_one_error_line
from helpers.run import REPO_ROOT, mbtool_env, run_cli

from mbtool.cli.commands.snapshot import write_requests


def test_a_dump_that_cannot_be_written_whole_leaves_the_previous_one(tmp_path):
    path = tmp_path / "device.toml"
    previous = "sparse = true\n\n[holding_registers]\n0 = [1, 2, 3]\n"
    path.write_text(previous)

    def small_files():  # a file size limit: the new dump cannot be written whole (EFBIG)
        resource.setrlimit(resource.RLIMIT_FSIZE, (200, 200))

    res = subprocess.run(
        [sys.executable, "-m", "mbtool", "dump", str(path), "--range", "holding:0-999", "-p", "sim://"],
        cwd=REPO_ROOT,
        env=mbtool_env(),
        preexec_fn=small_files,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert res.returncode == 7, res.stderr
    assert f"cannot write to {path}" in res.stderr and "Traceback" not in res.stderr
    assert path.read_text() == previous  # the previous dump, whole
    assert [p.name for p in tmp_path.iterdir()] == ["device.toml"]
    # Without the limit the new dump replaces it, with a new file's permissions.
    expect_ok_res = run_cli("dump", path, "--range", "holding:0-999", "-p", "sim://")
    assert expect_ok_res.returncode == 0, expect_ok_res.stderr
    assert tomllib.loads(path.read_text())["holding_registers"]
    assert [p.name for p in tmp_path.iterdir()] == ["device.toml"]


def test_a_dump_to_an_unwritable_place_fails_before_reading_the_device(tmp_path, silent_server):

    path = tmp_path / "no-such-folder" / "device.toml"
    line = assert_one_error_line(run_cli("dump", path, "-p", silent_server.tcp_target), 7)
    assert line == f"mbtool: cannot write to {path}: No such file or directory"
    assert silent_server.connections == 0 and silent_server.received_bytes() == b""


def test_diff_of_two_files_names_what_one_side_lacks(tmp_path):

    (tmp_path / "a.toml").write_text("sparse = true\n[holding_registers]\n0 = [1, 2, 3]\n[coils]\n4 = 1\n")
    (tmp_path / "b.toml").write_text("sparse = true\n[holding_registers]\n0 = [1, 5]\n[coils]\n4 = 1\n")
    res = run_cli("diff", tmp_path / "a.toml", tmp_path / "b.toml")
    assert res.returncode == 1
    assert res.stdout.splitlines() == ["holding 1: 2 -> 5", "holding 2: 3 -> missing"]
    res = run_cli("diff", tmp_path / "a.toml", tmp_path / "nothere.toml")
    assert res.returncode == 2 and "cannot read data file" in res.stderr


def test_write_requests_are_the_fewest_the_limits_allow():
    changes = {"holding": {a: a & 0xFFFF for a in [*range(0, 300), 400, 401, 500]}, "coils": {7: 1}}
    requests = write_requests(changes)
    assert [(r.function_code, r.address, len(r.values)) for r in requests] == [
        (0x0F, 7, 1),
        (0x10, 0, 123),
        (0x10, 123, 123),
        (0x10, 246, 54),
        (0x10, 400, 2),
        (0x10, 500, 1),
    ]
