"""The suite's own settings (issue 41): as many workers as the machine it runs on wants.

Most tests wait on sockets, pseudo-terminals and deadlines, so the suite runs several workers a
core; ten whatever the cores crowded a 1-core container and left a 16-core machine idle.
"""

from __future__ import annotations

import os
import tomllib

import pytest
from helpers.run import REPO_ROOT


def test_the_suite_asks_the_machine_how_many_workers():
    options = tomllib.loads((REPO_ROOT / "pyproject.toml").read_text())["tool"]["pytest"]["ini_options"]
    addopts = options["addopts"].split()
    assert addopts[addopts.index("-n") + 1] == "auto", addopts


@pytest.mark.parametrize("cores, workers", [(1, 5), (2, 10), (3, 15), (4, 16), (64, 16)])
def test_the_workers_are_five_a_core_at_most_sixteen(pytestconfig, monkeypatch, cores, workers):
    monkeypatch.delenv("PYTEST_XDIST_AUTO_NUM_WORKERS", raising=False)
    # The cores this process may run on (taskset, a container's cpuset), not the machine's.
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: set(range(cores)))
    # Through the hook, as pytest-xdist asks it for -n auto: ours answers before xdist's own.
    assert pytestconfig.hook.pytest_xdist_auto_num_workers(config=pytestconfig) == workers


def test_xdist_own_variable_still_says_how_many(pytestconfig, monkeypatch):
    monkeypatch.setenv("PYTEST_XDIST_AUTO_NUM_WORKERS", "3")
    assert pytestconfig.hook.pytest_xdist_auto_num_workers(config=pytestconfig) == 3
