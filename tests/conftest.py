"""Shared pytest fixtures."""

from __future__ import annotations

import pytest
import torch


@pytest.fixture(scope="module")
def one_thread():
    """One torch thread for a module of tiny-tensor tests: fastest, and 10-20x faster than two
    on a busy 2-core machine (spinning intra-op workers). Restores the previous count."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture
def fast_paths_on():
    """vggt_init's oneDNN/kernel fast paths switched on for the test, then restored."""
    from vggt_init.model import fastpath

    previous = fastpath.set_fast_paths(True)
    yield
    fastpath.set_fast_paths(previous)
