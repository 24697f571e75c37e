"""The fixtures of mbtool's tests, built on the helpers in tests/helpers/ (a module of each kind).

Peers mbtool talks to in these tests:

* an independent Modbus device: pymodbus's own server, run as a subprocess
  (tests/peers/pymodbus_device.py) on TCP (MBAP or RTU-over-TCP) or on one end of a
  pseudo-terminal pair;
* misbehaving peers in plain Python threads on 127.0.0.1: a silent TCP server, a raw
  responder that answers every request with bytes chosen by the test, and a port that
  refuses connections.

Every wait has a deadline; nothing here can hang the suite.
"""

from __future__ import annotations

import compileall
import contextlib
import itertools
import os
import shutil
import socket
import sys
from collections.abc import Callable
from pathlib import Path

import pytest
from helpers.devices import start_device
from helpers.ptys import PtyPair
from helpers.run import REPO_ROOT, TESTS_DIR, Result, run_mbtool
from helpers.served import serve
from helpers.sockets import RawResponder, SilentServer
from peers.certs import make_pki

E2E_DIR = Path(__file__).resolve().parent / "e2e"


def pytest_configure(config: pytest.Config) -> None:
    """Once a run, before the workers start: mbtool's bytecode, so that the ~430 mbtool
    processes the tests start read it rather than each compiling mbtool from source (0.35 s
    a process, where PYTHONDONTWRITEBYTECODE is set or the checkout is fresh: 20 s of a
    run).  It goes where Python itself would put it, mbtool/__pycache__ (ignored by git).
    And the test modules as pytest rewrites their asserts, when workers are to import them."""
    if not hasattr(config, "workerinput"):  # the controller (or a run without workers)
        compileall.compile_dir(REPO_ROOT / "mbtool", quiet=1)
        if getattr(config.option, "numprocesses", None):
            rewrite_test_modules_once(config)


def rewrite_test_modules_once(config: pytest.Config) -> None:
    """pytest rewrites the asserts of each test module it imports and keeps the result in the
    module's __pycache__, unless bytecode is not to be written (PYTHONDONTWRITEBYTECODE, as this
    machine and CI set): then every worker rewrote every module again, a worker's collection
    5.8 s of CPU where it is 1.7 s with them written: 40 s of a run of ten workers.  Written
    here once, the workers read them: pytest reads a rewritten module it finds whatever that
    setting.  This uses pytest's own functions for it (private, so a pytest without them is
    left to rewrite in each worker as before)."""
    try:
        from _pytest.assertion.rewrite import (
            PYC_TAIL,
            _read_pyc,
            _rewrite_test,
            _write_pyc,
            assertstate_key,
            get_cache_dir,
        )
    except ImportError:
        return
    state = config.stash[assertstate_key]
    paths = [Path(arg.split("::")[0]).resolve() for arg in config.args] or [TESTS_DIR]
    modules = {
        module
        for path in paths
        for module in (path.rglob("*.py") if path.is_dir() else [path])
        if (module.name.startswith("test_") or module.name == "conftest.py") and module.is_file()
    }
    try:
        for module in sorted(modules):
            cached = get_cache_dir(module) / (module.name[:-3] + PYC_TAIL)
            if _read_pyc(module, cached) is None:  # none yet, or of an older source
                source, code = _rewrite_test(module, config)
                with contextlib.suppress(OSError):  # a read-only checkout: the workers rewrite
                    cached.parent.mkdir(exist_ok=True)
                    _write_pyc(state, code, source, cached)
    except Exception:  # noqa: BLE001 - private functions a newer pytest may have changed (or a
        return  # module that does not compile, which its worker reports): the workers rewrite
    # pytest rewrites a plugin's whole distribution too: hypothesis (its pytest11 entry point),
    # 83 modules, 1 s of each worker.  Imported here with bytecode to be written, pytest's
    # import hook writes them as it would without PYTHONDONTWRITEBYTECODE.
    writes, sys.dont_write_bytecode = sys.dont_write_bytecode, False
    try:
        import hypothesis  # noqa: F401, PLC0415 - for the rewritten modules it leaves behind
    finally:
        sys.dont_write_bytecode = writes


# Most tests wait on sockets, pseudo-terminals and deadlines rather than compute, so the suite
# runs several workers a core: on 2 cores, one worker a core took 238 s, four 89 s, five 76-88 s,
# six 76 s.  Past some 16, the workers' own start-up (each imports mbtool and starts its
# session's devices) and memory cost more than the waits they overlap.
WORKERS_A_CORE = 5
MOST_WORKERS = 16


def workers_for(cores: int) -> int:
    return max(1, min(WORKERS_A_CORE * cores, MOST_WORKERS))


@pytest.hookimpl(tryfirst=True)
def pytest_xdist_auto_num_workers(config: pytest.Config) -> int | None:
    """``-n auto`` (pyproject's addopts): the workers for the cores this process may run on
    (its affinity, as taskset or a container's cpuset leave it), not the machine's count.
    PYTEST_XDIST_AUTO_NUM_WORKERS, where set, is pytest-xdist's to honour."""
    if os.environ.get("PYTEST_XDIST_AUTO_NUM_WORKERS"):
        return None
    return workers_for(len(os.sched_getaffinity(0)))


@pytest.hookimpl(tryfirst=True)  # before -m deselects by marker
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Every test under tests/e2e/ is end to end (``e2e``): ``pytest -m "not e2e"`` runs the rest.
    The order is the one xdist's work stealing (pyproject's --dist) is best at: it first hands
    each worker an equal run of consecutive tests, in this order, and later moves tests from the
    tail of the longest queue to a worker that ran out.  So each worker's run starts with a
    ``long`` test (one that takes half a minute, started last, would hold the whole run up by as
    much), then its share of the end-to-end tests, which mostly wait on peers and deadlines,
    and ends with its share of the others, short and busy: what is left to share out at the
    end is quick, and keeps the cores busy where the waits alone left them half idle."""
    for item in items:
        if item.path.is_relative_to(E2E_DIR):
            item.add_marker(pytest.mark.e2e)
    long = [item for item in items if item.get_closest_marker("long")]
    rest = [item for item in items if not item.get_closest_marker("long")]
    e2e = [item for item in rest if item.get_closest_marker("e2e")]
    ending = iter([item for item in rest if not item.get_closest_marker("e2e")])
    waiting = iter(e2e)
    workers = config.workerinput["workercount"] if hasattr(config, "workerinput") else 1
    ordered: list[pytest.Item] = []
    runs = zip(first_runs(len(items), workers), first_runs(len(e2e), workers), strict=True)
    for worker, (run, e2e_share) in enumerate(runs):
        first = long[worker::workers] + list(itertools.islice(waiting, e2e_share))
        ordered += first + list(itertools.islice(ending, max(0, run - len(first))))
    items[:] = ordered + list(waiting) + list(ending)


def first_runs(tests: int, workers: int) -> list[int]:
    """How many tests xdist's work stealing first sends each worker: the tests left shared
    evenly among the workers yet to get theirs (xdist.scheduler.worksteal's check_schedule)."""
    runs: list[int] = []
    for worker in range(workers):
        runs.append((tests - sum(runs)) // (workers - worker))
    return runs


@pytest.fixture
def mbtool() -> Callable[..., Result]:
    return run_mbtool


@pytest.fixture(scope="session")
def start_up() -> float:
    """Seconds an mbtool process takes to start and end on this machine as loaded now (the longer
    of two ``crc`` runs): what a test bounding a run's time allows above the run's deadlines."""
    return max(run_mbtool("crc", "01", "03").elapsed for _ in range(2))


@pytest.fixture
def pty_pair():
    """A bare pty pair with nothing on the device side (a silent serial line)."""
    pair = PtyPair()
    yield pair
    pair.close()


@pytest.fixture(scope="session")
def tcp_device():
    """pymodbus over Modbus TCP (MBAP); mbtool target tcp://127.0.0.1:PORT. Units 1 and 2."""
    with start_device(tcp=True, framer="socket") as dev:
        yield dev


@pytest.fixture(scope="session")
def socket_rtu_device():
    """pymodbus speaking RTU framing over a raw TCP socket; mbtool target socket://127.0.0.1:PORT."""
    with start_device(tcp=True, framer="rtu") as dev:
        yield dev


@pytest.fixture(scope="session")
def serial_rtu_device():
    """pymodbus RTU on one end of a pty pair; mbtool target is the other end's path."""
    with start_device(tcp=False, framer="rtu") as dev:
        yield dev


@pytest.fixture(scope="session")
def serial_ascii_device():
    """pymodbus ASCII on one end of a pty pair."""
    with start_device(tcp=False, framer="ascii") as dev:
        yield dev


@pytest.fixture(scope="session")
def holed_device():
    """pymodbus over Modbus TCP with gaps in its address map (pymodbus_device.HOLED): a read
    that touches one answers exception 02. Unit 1."""
    with start_device(tcp=True, framer="socket", units="1", holes=True) as device:
        yield device


NOT_FINITE = """\
[holding_registers]
0 = [0x7FC0, 0x0000, 0x7F80, 0x0000, 0xFF80, 0x0000, 0x41AC, 0x0000]  # NaN, +Inf, -Inf, 21.5
"""

NOT_FINITE_MAP = """\
[device]
type = "float32"
[points.nan]
ref = 40001
[points.inf]
ref = 40003
[points.minus_inf]
ref = 40005
[points.fine]
ref = 40007
"""


@pytest.fixture(scope="session")
def not_finite(tmp_path_factory):
    """mbtool serve with float32 NaN, +Inf, -Inf and 21.5 in holding registers 0-7, and a map."""
    where = tmp_path_factory.mktemp("not-finite")
    (where / "data.toml").write_text(NOT_FINITE)
    (where / "map.toml").write_text(NOT_FINITE_MAP)
    with serve("--data", str(where / "data.toml")) as server:
        server.map = where / "map.toml"
        yield server


@pytest.fixture(scope="session")
def pki(tmp_path_factory):
    """A CA and the certificates the TLS tests need, made by ``openssl`` into a tmp dir
    (tests/peers/certs.py: with and without the role extension, expired, for another name,
    self-signed, from an unknown CA); never committed keys."""
    if shutil.which("openssl") is None:
        pytest.skip("the openssl command is not installed (Debian: apt-get install openssl)")
    return make_pki(tmp_path_factory.mktemp("pki"))


@pytest.fixture
def pymodbus_tcp_client(tcp_device):
    """pymodbus's own client on the tcp_device: the independent check of what mbtool wrote."""
    from pymodbus.client import ModbusTcpClient

    client = ModbusTcpClient(tcp_device.host, port=tcp_device.port, timeout=2, retries=1)
    assert client.connect(), "pymodbus client cannot connect to the device"
    yield client
    client.close()


@pytest.fixture
def pymodbus_rtu_socket_client(socket_rtu_device):
    from pymodbus import FramerType
    from pymodbus.client import ModbusTcpClient

    client = ModbusTcpClient(
        socket_rtu_device.host, port=socket_rtu_device.port, framer=FramerType.RTU, timeout=2, retries=1
    )
    assert client.connect()
    yield client
    client.close()


@pytest.fixture
def silent_server():
    srv = SilentServer()
    yield srv
    srv.close()


@pytest.fixture
def raw_responder():
    """Factory: raw_responder(reply_bytes_or_callable) -> RawResponder (closed after the test)."""
    made: list[RawResponder] = []

    def make(reply, port: int = 0):
        srv = RawResponder(reply, port)
        made.append(srv)
        return srv

    yield make
    for srv in made:
        srv.close()


@pytest.fixture
def refused_port():
    """A port bound on 127.0.0.1 but not listening: connecting gets ECONNREFUSED."""
    s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    s.bind(("127.0.0.1", 0))
    yield s.getsockname()[1]
    s.close()
