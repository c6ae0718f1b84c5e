"""Shared pytest fixtures, and the Hypothesis profile every property test runs under.

Hypothesis profiles (``HYPOTHESIS_PROFILE``):

* ``ci`` (the default): derandomised. The examples are a fixed function of each test's code,
  so a clean-clone run's outcome does not depend on chance (a CI failure blocks
  every landing). No example database is read or written.
* ``explore``: random examples, five times as many, with the example database; for hunting
  new counter-examples locally (``HYPOTHESIS_PROFILE=explore pytest -k "given or property"``).
  A counter-example found there becomes a fixed ``@example`` next to the test.
"""

from __future__ import annotations

import os

import pytest
import torch
from hypothesis import settings

settings.register_profile("ci", derandomize=True, database=None, deadline=None, print_blob=True)
settings.register_profile("explore", derandomize=False, deadline=None, print_blob=True,
                          max_examples=5 * settings.default.max_examples)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci"))


@pytest.fixture(scope="module")
def one_thread():
    """One torch thread for a module of tiny-tensor tests: fastest, and 10-20x faster than two
    on a busy 2-core machine (spinning intra-op workers). Restores the previous count."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture(scope="module")
def two_threads():
    """Two torch threads for a module (the CI machine's cores), restored afterwards: a module
    that set the count at import time changed it for every test collected after it."""
    n = torch.get_num_threads()
    torch.set_num_threads(2)
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
