"""Shared pytest fixtures, and the Hypothesis profile every property test runs under.

Hypothesis profiles (``HYPOTHESIS_PROFILE``):

* ``ci`` (the default): derandomised. The examples are a fixed function of each test's code,
  so a clean-clone run's outcome does not depend on chance (a CI failure blocks
  every landing). No example database is read or written.
* ``explore``: random examples, five times as many, with the example database; for hunting
  new counter-examples locally (``HYPOTHESIS_PROFILE=explore pytest -k "given or property"``).
  A counter-example found there becomes a fixed ``@example`` next to the test.

Parallel runs (pytest-xdist, ``make test``: ``-n auto --dist loadfile``): each worker gets an
equal share of the cores for torch and for the processes its tests start (``OMP_NUM_THREADS``),
so two workers on two cores do not fight over them; a test file is one unit of work (its
module fixtures are made once), the files that read the shared end-to-end run
(``workflow_run``) are one unit together (the run is made once), and units with a slow test
start first. At the end the terminal summary lists the slowest files (with ``--durations``).
"""

from __future__ import annotations

import os
import re
import time
from collections import defaultdict

import pytest
import torch
from hypothesis import settings

settings.register_profile("ci", derandomize=True, database=None, deadline=None, print_blob=True)
settings.register_profile("explore", derandomize=False, deadline=None, print_blob=True,
                          max_examples=5 * settings.default.max_examples)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci"))


def _usable_cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


def _worker_count(config) -> int:
    """pytest-xdist's number of workers, seen from a worker; 0 in a plain (serial) run."""
    workerinput = getattr(config, "workerinput", None)
    return int(workerinput["workercount"]) if workerinput else 0


#: ``-n auto``'s most workers: beyond about eight the longest unit of work (the shared
#: end-to-end run) sets the suite's time, and each worker holds its own torch (0.5-1.5 GB)
MAX_AUTO_WORKERS = 8


@pytest.hookimpl(optionalhook=True)  # pytest-xdist's hook
def pytest_xdist_auto_num_workers(config):
    """``-n auto``: one worker per core this process may use (logical cores, so a 2-vCPU CI
    machine gets two, where xdist's own count of physical cores can say one), at most
    :data:`MAX_AUTO_WORKERS`; ``PYTEST_XDIST_AUTO_NUM_WORKERS`` still decides where it is set."""
    if os.environ.get("PYTEST_XDIST_AUTO_NUM_WORKERS"):
        return None
    return min(_usable_cores(), MAX_AUTO_WORKERS)


def pytest_configure(config):
    workers = _worker_count(config)
    if workers:
        share = max(1, _usable_cores() // workers)
        torch.set_num_threads(share)
        os.environ["OMP_NUM_THREADS"] = os.environ["MKL_NUM_THREADS"] = str(share)


def _cores_for_this_process(config) -> int:
    workers = _worker_count(config)
    return max(1, _usable_cores() // workers) if workers else _usable_cores()


#: a test that reads the shared end-to-end run (seen in its file's source by the controller,
#: which collects nothing itself; a file missed here only costs a second run on another worker)
_READS_SHARED_RUN = re.compile(r"^def test\w*\([^)]*\bworkflow_run\b", re.M)


@pytest.hookimpl(tryfirst=True, optionalhook=True)  # pytest-xdist's hook
def pytest_xdist_make_scheduler(config, log):
    """``--dist loadfile`` with one change: the files whose tests read the shared end-to-end run
    (fixture ``workflow_run``) are one unit of work together, so the run is made once. Units
    go out in the workers' collection order (see :func:`pytest_collection_modifyitems`)."""
    if config.getvalue("dist") != "loadfile":
        return None
    from xdist.scheduler import LoadFileScheduling

    if hasattr(config.option, "loadscopereorder"):
        config.option.loadscopereorder = False  # by test count; ours puts the longest units first
    shared: dict[str, bool] = {}

    def reads_shared_run(path: str) -> bool:
        if path not in shared:
            source = config.rootpath / path
            shared[path] = source.is_file() and bool(_READS_SHARED_RUN.search(source.read_text()))
        return shared[path]

    class SharedRunWithItsReaders(LoadFileScheduling):
        def _split_scope(self, nodeid: str) -> str:
            path = super()._split_scope(nodeid)
            return "workflow_run" if reads_shared_run(path) else path

    return SharedRunWithItsReaders(config, log)


def pytest_collection_modifyitems(config, items):
    """On a pytest-xdist worker: the files that read the shared end-to-end run first, then those
    with a ``slow`` test, then the rest (longest first is the better schedule on two workers);
    the same order on every worker, as xdist requires. A serial run keeps the file order."""
    if not _worker_count(config):
        return
    shared = {item.path for item in items if "workflow_run" in item.fixturenames}
    slow = {item.path for item in items if item.get_closest_marker("slow")}
    first_seen: dict = {}
    for item in items:
        first_seen.setdefault(item.path, len(first_seen))
    items.sort(key=lambda item: (item.path not in shared, item.path not in slow, first_seen[item.path]))


_FILE_SECONDS: defaultdict[str, float] = defaultdict(float)
_SESSION_START: list[float] = []


def pytest_sessionstart(session):
    _SESSION_START.append(time.monotonic())


def pytest_runtest_logreport(report):
    _FILE_SECONDS[report.nodeid.split("::")[0]] += report.duration


def pytest_terminal_summary(terminalreporter, config):
    """The slowest test files (setup, call and teardown of all their tests), beside
    ``--durations``' slowest tests, and the tests' seconds in all against the run's (under
    xdist the workers' seconds overlap: their ratio is how parallel the run was)."""
    if config.getoption("durations", None) is None or not _FILE_SECONDS:
        return
    terminalreporter.write_sep("=", "slowest 15 test files")
    for path, secs in sorted(_FILE_SECONDS.items(), key=lambda kv: -kv[1])[:15]:
        terminalreporter.write_line(f"{secs:8.2f}s {path}")
    total, wall = sum(_FILE_SECONDS.values()), max(time.monotonic() - _SESSION_START[0], 1e-6)
    terminalreporter.write_line(f"{total:8.2f}s in all {len(_FILE_SECONDS)} files, in {wall:.0f} s of wall time "
                                f"({total / wall:.2f} tests at a time on average)")


@pytest.fixture(scope="module")
def one_thread():
    """One torch thread for a module of tiny-tensor tests: fastest, and 10-20x faster than two
    on a busy 2-core machine (spinning intra-op workers). Restores the previous count."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture(scope="module")
def core_threads(pytestconfig):
    """One torch thread per core this process may use (all of them in a serial run, its share
    under pytest-xdist), restored afterwards: a module that set the count at import time
    changed it for every test collected after it."""
    n = torch.get_num_threads()
    torch.set_num_threads(_cores_for_this_process(pytestconfig))
    yield
    torch.set_num_threads(n)


@pytest.fixture
def fast_paths_on():
    """vggt_init's oneDNN/kernel fast paths switched on for the test, then restored."""
    from vggt_init.model import fastpath

    previous = fastpath.set_fast_paths(True)
    yield
    fastpath.set_fast_paths(previous)


@pytest.fixture(scope="session")
def workflow_run(tmp_path_factory):
    """The end-to-end Snakemake run shared by every test that reads a whole DAG's outputs: one
    per pytest run, made on first use (tests/_workflow_run.py has its config). Skips where
    Snakemake or the VGGT fixture model is missing."""
    from _workflow_run import FIXTURE, SNAKEMAKE_MISSING, run_shared_workflow

    if SNAKEMAKE_MISSING:
        pytest.skip("snakemake is not installed")
    if not (FIXTURE / "weights.safetensors").is_file():
        pytest.skip("VGGT fixture missing")
    return run_shared_workflow(tmp_path_factory.mktemp("workflow_run"))
