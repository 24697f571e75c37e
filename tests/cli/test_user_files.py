"""The files a user names, read whole: register maps, poll's inventories, serve's --data files
and profiles (issue 40.12).  A character device (/dev/zero), a FIFO or a file past the size
bound is refused with exit 2, one line, at once: never read forever (memory grows until the
kernel kills it) nor waited on (a FIFO nobody writes).  Each run is a process of its own with
its address space capped, so a reader that does run away fails fast instead of taking the
machine's memory, and with a deadline, so one that waits fails too."""

from __future__ import annotations

import os
import resource
import subprocess
import sys

import pytest
from helpers.run import REPO_ROOT, mbtool_env, signals_as_from_a_shell

from mbtool.files import MAX_FILE_BYTES

pytestmark = pytest.mark.timeout(60)


def _capped() -> None:
    signals_as_from_a_shell()
    resource.setrlimit(resource.RLIMIT_AS, (1 << 30, 1 << 30))  # 1 GiB: /dev/zero read whole fails fast


def _run(*args, env=None) -> subprocess.CompletedProcess:
    try:
        return subprocess.run(
            [sys.executable, "-m", "mbtool", *map(str, args)],
            cwd=REPO_ROOT,
            env=mbtool_env(env),
            preexec_fn=_capped,
            stdin=subprocess.DEVNULL,
            capture_output=True,
            text=True,
            timeout=15,
        )
    except subprocess.TimeoutExpired:
        pytest.fail(f"mbtool {' '.join(map(str, args))} still reading after 15 s")


@pytest.fixture(params=["/dev/zero", "fifo", "too-big", "directory"])
def hostile(request, tmp_path):
    """A path that is no file to read whole: a device, a FIFO no one writes, a sparse file
    past the bound."""
    if request.param == "fifo":
        path = tmp_path / "named.toml"
        os.mkfifo(path)
        return path, "not a regular file"
    if request.param == "too-big":
        path = tmp_path / "huge.toml"
        with open(path, "wb") as file:
            file.truncate(MAX_FILE_BYTES + 1)
        return path, "larger than"
    if request.param == "directory":
        return tmp_path, "directory"  # on the command line, click says so first
    return request.param, "not a regular file"


def _refused(res: subprocess.CompletedProcess, path, words: str) -> None:
    assert res.returncode == 2, (res.returncode, res.stderr[-2000:])
    lines = res.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("mbtool: "), res.stderr[-2000:]
    assert str(path) in lines[0] and words in lines[0], lines[0]


def test_a_map_that_is_not_a_regular_file_is_refused(hostile):
    path, words = hostile
    _refused(_run("read", "-m", path, "-p", "sim://"), path, words)


def test_an_inventory_and_a_map_it_names_that_are_not_regular_files_are_refused(hostile, tmp_path):
    path, words = hostile
    _refused(_run("poll", path, "--once"), path, words)
    plant = tmp_path / "plant.toml"
    plant.write_text(f'[links.a]\ntarget = "sim://"\n[devices.d]\nlink = "a"\nmap = "{path}"\n')
    _refused(_run("poll", plant, "--once"), path, words)


def test_a_data_file_that_is_not_a_regular_file_is_refused(hostile):
    path, words = hostile
    _refused(_run("serve", "-p", "tcp://127.0.0.1:0", "--data", path), path, words)


def test_a_profile_file_that_is_not_a_regular_file_is_refused(hostile):
    path, words = hostile
    res = _run("read", "40001", "-P", "boiler", env={"MBTOOL_CONFIG": str(path)})
    _refused(res, path, words)
