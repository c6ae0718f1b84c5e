"""runtime.native.stoppable: a call in a forked child, its result or error handed back."""

from __future__ import annotations

import os

import pytest

from runtime.native import stoppable


def _pair(a, b=0):
    return {"sum": a + b, "pid": os.getpid()}


def _refuse(x):
    raise ValueError(f"bad {x}")


def test_the_result_comes_back_from_a_child():
    got = stoppable("adding", _pair, 2, b=3)
    assert got["sum"] == 5 and got["pid"] != os.getpid()


def test_the_childs_exception_is_raised_here():
    with pytest.raises(ValueError, match="bad 7"):
        stoppable("refusing", _refuse, 7)


def test_a_crashed_call_is_a_runtime_error_naming_it():
    with pytest.raises(RuntimeError, match=r"feature extraction ended without a result \(signal SIGABRT\)"):
        stoppable("feature extraction", os.abort)


def test_a_result_that_does_not_pickle_is_named():
    with pytest.raises(RuntimeError, match="pickle"):
        stoppable("a lambda", lambda: (lambda: 0))
