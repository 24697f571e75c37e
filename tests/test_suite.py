"""The suite's own settings (issue 41): as many workers as the machine it runs on wants.

Most tests wait on sockets, pseudo-terminals and deadlines, so the suite runs several workers a
core; ten whatever the cores crowded a 1-core container and left a 16-core machine idle.
"""

from __future__ import annotations

import os
import sys
import tomllib
from types import SimpleNamespace

import conftest
import pytest
from helpers.run import REPO_ROOT
from xdist.scheduler import WorkStealingScheduling


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


def test_the_test_modules_are_rewritten_once_before_the_workers_start(pytestconfig, tmp_path, monkeypatch):
    """With bytecode not to be written (PYTHONDONTWRITEBYTECODE, as CI sets), pytest leaves each
    worker to rewrite every test module's asserts itself; the run writes them once instead, where
    pytest reads them whatever that setting."""
    from _pytest.assertion.rewrite import PYC_TAIL, _read_pyc, get_cache_dir

    module = tmp_path / "test_sample.py"
    module.write_text("def test_sum():\n    assert 1 + 1 == 3\n")
    monkeypatch.setattr(sys, "dont_write_bytecode", True)
    monkeypatch.setattr(pytestconfig, "args", [str(tmp_path)])
    conftest.rewrite_test_modules_once(pytestconfig)
    code = _read_pyc(module, get_cache_dir(module) / (module.name[:-3] + PYC_TAIL))
    assert code is not None, "no rewritten module written"
    assert "@pytest_ar" in code.co_names  # pytest's rewritten asserts, not a plain compile
    assert sys.dont_write_bytecode


class _Test:
    """What the ordering hook asks of a collected test: its path and its markers."""

    def __init__(self, name: str, long: bool = False, e2e: bool = False) -> None:
        self.name, self.long = name, long
        self.path = REPO_ROOT / "tests" / ("e2e" if e2e else "codec") / "test_x.py"
        self.markers = {"long"} if long else set()

    def add_marker(self, marker) -> None:
        self.markers.add(marker.name)

    def get_closest_marker(self, name: str):
        return name in self.markers or None


class _Worker:
    """What xdist's scheduler asks of a worker: the tests it is sent."""

    def __init__(self, name: str) -> None:
        self.gateway, self.shutting_down, self.sent = SimpleNamespace(id=name), False, []

    def send_runtest_some(self, indices: list[int]) -> None:
        self.sent.extend(indices)


def handed_out(items: list[_Test], workers: int) -> list[list[_Test]]:
    """The tests xdist's work stealing first sends each worker, ``items`` in the order the
    suite's hook left them."""
    scheduler = WorkStealingScheduling(SimpleNamespace(getvalue={"tx": ["popen"] * workers}.get))
    nodes = [_Worker(f"gw{n}") for n in range(workers)]
    for node in nodes:
        scheduler.add_node(node)
        scheduler.add_node_collection(node, [item.name for item in items])
    scheduler.schedule()
    return [[items[index] for index in node.sent] for node in nodes]


@pytest.mark.parametrize("longs, workers", [(3, 10), (12, 5)])
def test_each_long_test_starts_first_on_a_worker_of_its_own(longs, workers):
    """xdist's work stealing (pyproject's --dist) first hands each worker an equal run of
    consecutive tests, then moves tests from the tail of the longest queue to a worker that is
    done: a long test at the head of each run starts at once, and no worker gets two of them
    while another has none (all at the front went to one worker, one after the other)."""
    options = tomllib.loads((REPO_ROOT / "pyproject.toml").read_text())["tool"]["pytest"]["ini_options"]
    addopts = options["addopts"].split()
    assert addopts[addopts.index("--dist") + 1] == "worksteal", addopts
    items = [_Test(f"t{n}") for n in range(400)] + [_Test(f"long{n}", long=True) for n in range(longs)]
    conftest.pytest_collection_modifyitems(SimpleNamespace(workerinput={"workercount": workers}), items)
    assert [item.name for item in items if not item.long] == [f"t{n}" for n in range(400)]
    for worker, run in enumerate(handed_out(items, workers)):
        kinds = [item.long for item in run]
        heading = kinds.index(False)
        assert not any(kinds[heading:]), f"gw{worker} runs a long test after a short one"
        assert heading == len(range(worker, longs, workers))  # its share of them, first


def test_each_worker_waits_on_peers_first_and_ends_with_the_short_busy_tests():
    """Behind its long test each worker's run has its share of the end-to-end tests, which
    mostly wait on peers and deadlines, and then its share of the others: what the workers
    steal at the end is short, and busy where the waits alone left the cores half idle (the
    end-to-end tests, collected together, had made four workers' runs of nothing else)."""
    items = (
        [_Test(f"c{n}") for n in range(300)]
        + [_Test(f"e{n}", e2e=True) for n in range(100)]
        + [_Test(f"u{n}") for n in range(60)]
        + [_Test(f"long{n}", long=True) for n in range(3)]
    )
    conftest.pytest_collection_modifyitems(SimpleNamespace(workerinput={"workercount": 10}), items)
    kinds = {"c": "other", "u": "other", "e": "e2e", "l": "long"}
    for kind in ("e2e", "other"):  # each kind in the order it was collected
        names = [item.name for item in items if kinds[item.name[0]] == kind]
        assert names == sorted(names, key=lambda name: ("cue".index(name[0]), int(name[1:])))
    for worker, run in enumerate(handed_out(items, 10)):
        order = [kinds[item.name[0]] for item in run]
        assert order == sorted(order, key=["long", "e2e", "other"].index), f"gw{worker}: {order}"
        assert order.count("e2e") == 10, f"gw{worker}: {order}"  # its share of the 100
