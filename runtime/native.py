"""A long native call that a stop signal can end at once: :func:`stoppable`.

Python runs a signal handler between two bytecodes of the main thread, so a stop (SIGTERM,
SIGINT, SIGHUP: :mod:`runtime.stops`) that comes during one long native call (a pycolmap
feature extraction, matching, mapping, triangulation or bundle adjustment: minutes on a real
scene) would take effect only when the call returns. :func:`stoppable` runs the call in a
forked child process instead, while this process waits on a pipe, a wait that a signal
interrupts: on a stop the child is killed (SIGKILL) and reaped *before* the stop goes on, so
that no native code is still writing into the scratch folder that the cleanup then removes,
and the command ends within a second with :func:`runtime.stops.stop_line`'s line.

The child is a copy of this process (fork): it sees every object, option and seed the caller
set (pycolmap's global PRNG included), but what it changes in memory stays in the child. Its
result comes back pickled; a call whose result does not pickle (a ``pycolmap.Reconstruction``)
is wrapped by its caller in a function that writes the result to the scratch folder and returns
what pickles. The child ignores the stop signals (a terminal's Ctrl-C reaches the whole process
group; the parent decides) and dies with its parent (``PR_SET_PDEATHSIG``). An exception in the
child is raised again here; a child that crashes (a native abort) is a ``RuntimeError`` naming
the call and the signal, not a dead command. Where the platform has no ``fork`` the call runs
in this process, and a stop takes effect when it returns.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import pickle
import signal
from typing import Callable, TypeVar

from runtime.stops import STOP_SIGNALS, stops_held

__all__ = ["stoppable"]

T = TypeVar("T")

_PR_SET_PDEATHSIG = 1


def _die_with_parent() -> None:
    """Linux: the kernel kills this (child) process when its parent dies, even by SIGKILL."""
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0)


def _child_main(fn: Callable, args: tuple, kwargs: dict, r: int, w: int) -> None:
    """The forked child (the stop signals still blocked by the parent's hold): ignore them,
    run :func:`_child` and end without running the parent's cleanup or exit handlers."""
    code = 0
    try:
        for s in STOP_SIGNALS:
            signal.signal(s, signal.SIG_IGN)
        signal.pthread_sigmask(signal.SIG_UNBLOCK, STOP_SIGNALS)
        _die_with_parent()
        os.close(r)
        _child(fn, args, kwargs, w)
    except BaseException:  # noqa: BLE001 - the parent reports a child without a reply
        code = 1
    finally:
        os._exit(code)


def _child(fn: Callable[..., T], args: tuple, kwargs: dict, w: int) -> None:
    """Run ``fn`` and write ``("ok", result)`` or ``("err", exception)`` to ``w``, pickled."""
    try:
        reply = ("ok", fn(*args, **kwargs))
    except BaseException as exc:  # noqa: BLE001 - handed to the parent, which raises it
        reply = ("err", exc)
    try:
        data = pickle.dumps(reply)
    except Exception as exc:  # noqa: BLE001 - a result or exception that does not pickle
        data = pickle.dumps(("err", RuntimeError(f"{type(exc).__name__}: {exc}" if reply[0] == "ok"
                                                 else f"{type(reply[1]).__name__}: {reply[1]}")))
    view = memoryview(data)
    while view:
        view = view[os.write(w, view):]


def stoppable(what: str, fn: Callable[..., T], *args, **kwargs) -> T:
    """``fn(*args, **kwargs)`` in a forked child process that a stop ends at once (module doc).

    Args:
        what: the call in words, for an error (``"feature extraction"``).
        fn: the call; its result and exceptions must pickle (else a ``RuntimeError`` says so).

    Returns:
        ``fn``'s result.

    Raises:
        whatever ``fn`` raised; ``RuntimeError`` when the child died without a reply (a native
        crash); the stop (:class:`runtime.stops.Stopped`, ``KeyboardInterrupt``) after the child
        was killed and reaped.
    """
    if not hasattr(os, "fork"):  # no fork (Windows): the call runs here, and a stop waits for it
        return fn(*args, **kwargs)
    r, w = os.pipe()
    pid = None
    try:
        with stops_held():  # a stop during the fork waits for both sides to be set up
            pid = os.fork()
            if pid == 0:  # the child: never returns into the caller's code
                _child_main(fn, args, kwargs, r, w)
        os.close(w)
        w = None
        chunks = []
        while True:
            chunk = os.read(r, 1 << 20)  # a stop signal's handler raises here (PEP 475)
            if not chunk:
                break
            chunks.append(chunk)
        _, status = os.waitpid(pid, 0)
        pid = None
    except BaseException:
        if pid:
            with contextlib.suppress(OSError):
                os.kill(pid, signal.SIGKILL)
            with contextlib.suppress(OSError):
                os.waitpid(pid, 0)  # reaped: nothing of the call writes any more
        raise
    finally:
        for fd in (r, w):
            if fd is not None:
                os.close(fd)
    if not chunks:
        how = (f"signal {signal.Signals(-os.waitstatus_to_exitcode(status)).name}"
               if os.WIFSIGNALED(status) else f"exit code {os.waitstatus_to_exitcode(status)}")
        raise RuntimeError(f"{what} ended without a result ({how}): the native call crashed")
    kind, value = pickle.loads(b"".join(chunks))
    if kind == "err":
        raise value
    return value
