"""Atomic writes leave nothing behind on an exception and replace outputs whole."""

from __future__ import annotations

import json

import numpy as np
import pytest

from runtime.atomic import atomic_dir, atomic_path, save_npz, write_json


def test_atomic_path_success_and_failure(tmp_path):
    target = tmp_path / "sub" / "out.txt"
    with atomic_path(target) as tmp:
        assert tmp.suffix == ".txt" and tmp.parent == target.parent
        tmp.write_text("new")
    assert target.read_text() == "new"
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_text("half")
            raise RuntimeError("boom")
    assert target.read_text() == "new"
    assert [p.name for p in target.parent.iterdir()] == ["out.txt"]


def test_atomic_dir_success_replace_and_failure(tmp_path):
    d = tmp_path / "model"
    with atomic_dir(d) as tmp:
        (tmp / "a.txt").write_text("1")
    with atomic_dir(d) as tmp:
        (tmp / "b.txt").write_text("2")
    assert sorted(p.name for p in d.iterdir()) == ["b.txt"]  # replaced as a whole
    with pytest.raises(KeyError):
        with atomic_dir(d) as tmp:
            (tmp / "c.txt").write_text("3")
            raise KeyError("boom")
    assert sorted(p.name for p in d.iterdir()) == ["b.txt"]
    assert [p.name for p in tmp_path.iterdir()] == ["model"]
    with pytest.raises(ValueError):
        with atomic_dir(tmp_path / "fresh"):
            raise ValueError
    assert [p.name for p in tmp_path.iterdir()] == ["model"]


def test_write_json_and_npz(tmp_path):
    p = write_json(tmp_path / "a.json", {"x": np.float32(1.5), "n": np.nan, "arr": np.arange(3), 1: tmp_path})
    data = json.loads(p.read_text())
    assert data == {"x": 1.5, "n": None, "arr": [0, 1, 2], "1": str(tmp_path)}
    with pytest.raises(TypeError):
        write_json(tmp_path / "b.json", {"x": object()})
    assert sorted(q.name for q in tmp_path.iterdir()) == ["a.json"]
    q = save_npz(tmp_path / "z.npz", a=np.arange(4))
    np.testing.assert_array_equal(np.load(q)["a"], np.arange(4))


def test_atomic_outputs_follow_umask(tmp_path):
    """Outputs are readable by others as with a plain open() (mkstemp alone gives 0600)."""
    import os
    import stat

    from runtime.atomic import atomic_dir, write_json

    old = os.umask(0o022)
    try:
        write_json(tmp_path / "a.json", {"x": 1})
        with atomic_dir(tmp_path / "d") as d:
            (d / "f").write_text("x")
    finally:
        os.umask(old)
    assert stat.S_IMODE((tmp_path / "a.json").stat().st_mode) == 0o644
    assert stat.S_IMODE((tmp_path / "d").stat().st_mode) == 0o755


class _Stop(BaseException):
    pass


@pytest.mark.skipif(not hasattr(__import__("signal"), "pthread_sigmask"), reason="no pthread_sigmask here")
@pytest.mark.parametrize("writer, maker", [(atomic_dir, "mkdtemp"), (atomic_path, "mkstemp")])
def test_a_stop_signal_while_the_temporary_name_is_made_leaves_nothing(tmp_path, monkeypatch, writer, maker):
    """A SIGTERM that lands right after the temporary file or folder exists, before the writer's
    ``try`` (where a loaded machine can deschedule a stage), still leaves nothing behind."""
    import signal
    import tempfile
    import threading

    made = getattr(tempfile, maker)

    def make_then_stop(*args, **kwargs):
        out = made(*args, **kwargs)
        # to this thread (a signal to the process may go to another thread, which holds nothing
        # back): delivered at once unless the writer holds it back
        signal.pthread_kill(threading.get_ident(), signal.SIGTERM)
        return out

    def raise_stop(signum, frame):
        raise _Stop

    previous = signal.signal(signal.SIGTERM, raise_stop)
    monkeypatch.setattr(tempfile, maker, make_then_stop)
    try:
        with pytest.raises(_Stop):
            with writer(tmp_path / "out") as tmp:
                (tmp / "a.txt" if tmp.is_dir() else tmp).write_text("never")
    finally:
        signal.signal(signal.SIGTERM, previous)
    assert list(tmp_path.iterdir()) == []
