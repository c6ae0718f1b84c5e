"""Stopping a command: SIGTERM, SIGINT and SIGHUP become one exception, :class:`Stopped`.

Snakemake and SLURM cancel a job with SIGTERM, a terminal sends SIGHUP when it closes and
SIGINT on Ctrl-C. While :func:`stops_caught` is active (``runtime.outdir.run_stage`` holds it
around every stage command) each of them raises :class:`Stopped` in the main thread, so every
``finally`` runs: temporary files and folders are removed, locks given up, and the command ends
with one line and exit code 128 + the signal (SIGHUP 129, SIGINT 130, SIGTERM 143).

Native libraries can take these signals over when they are loaded: pycolmap's glog installs a
crash handler for SIGTERM that prints a stack dump and kills the process, so no cleanup would
run. The modules listed in :data:`NATIVE_HANDLERS` are therefore watched while the handlers are
active: right after such a module is imported (pycolmap is imported lazily, inside a stage's
work), the handlers are installed again.

:func:`stops_held` holds the signals back for a few lines of bookkeeping that must not be cut
in half (``runtime.atomic``'s temporary names, ``runtime.ledger``'s markers, the lock that
``runtime.outdir.prepare_out`` takes).
:func:`run_command` is the ending of a command without an output folder (a benchmark runner);
:func:`run_child` runs a child command and passes a stop on to it, waiting for its cleanup.

A signal ignored when the command started stays ignored (``nohup`` ignores SIGHUP, a shell
ignores SIGINT in the jobs it starts in the background).

Before :func:`stops_caught` takes over, while a command is still loading (numpy, torch and
pycolmap take a second or more to import) and parsing its arguments, :func:`stops_early` ends it
at once with the same line and exit code: each stage package calls :func:`early_if_main` first
in its ``__init__``, which acts only when the process was started with ``python -m``. A stop
that lands inside a native module's initialisation surfaces as that module's ``ImportError``;
:func:`stopping` tells the command's ending that it was a stop.

Python runs a handler between two bytecodes of the main thread, so a stop that comes during one
long native call would take effect only when that call returns: the long pycolmap calls
(feature extraction, matching, mapping, triangulation, bundle adjustment) therefore run through
:func:`runtime.native.stoppable`, in a child process that a stop kills and reaps at once.
"""

from __future__ import annotations

import contextlib
import importlib.abc
import importlib.machinery
import logging
import os
import signal
import subprocess
import sys
import threading
from typing import Callable, Iterator

__all__ = ["Stopped", "STOP_SIGNALS", "NATIVE_HANDLERS", "CHILD_GRACE_S", "stops_caught", "stops_held", "stop_line",
           "stopping", "stops_early", "early_if_main", "run_command", "run_child"]

STOP_SIGNALS = (signal.SIGTERM, signal.SIGINT, signal.SIGHUP)
"""The signals that stop a command."""

NATIVE_HANDLERS = frozenset({"pycolmap"})
"""Top-level modules whose import installs native handlers for a stop signal (found by reading
``sigaction`` before and after importing each of the project's native dependencies: pycolmap
installs glog's for SIGTERM; torch, open3d, OpenImageIO, pyarrow and gsplat install none)."""


CHILD_GRACE_S = 30.0
"""How long a stopped command waits for a child command it passed the stop on to (SLURM's
default ``KillWait`` between SIGTERM and SIGKILL is 30 s); then the child is killed."""


class Stopped(BaseException):
    """The process was asked to stop (SIGTERM, SIGINT, SIGHUP): raised in the main thread so
    that every ``finally`` runs (temporary files and folders of ``runtime.atomic`` are removed).
    Not an ``Exception``, so ``except Exception`` never swallows it."""

    def __init__(self, signum: int):
        super().__init__(signum)
        self.signum = int(signum)
        self.name = signal.Signals(signum).name


def stop_line(exc: BaseException) -> tuple[str, int]:
    """The one line a stopped command ends with and its exit code (128 + the signal), for a
    :class:`Stopped` or a ``KeyboardInterrupt`` (SIGINT while Python's own handler was in place)."""
    signum = exc.signum if isinstance(exc, Stopped) else int(signal.SIGINT)
    name = signal.Signals(signum).name
    return (f"stopped by {name}: nothing half-written was kept (outputs are written atomically); "
            "run the same command again", 128 + signum)


_STOPPING: list[int] = []
"""The signal that is stopping the command, once :class:`Stopped` has been raised."""

_HELD: list[bool] = []
"""One entry per :func:`stops_held` block now open (in any thread)."""

_PENDING: list[int] = []
"""A stop signal that came while a :func:`stops_held` block was open."""


def _stop(signum, frame) -> None:
    if _STOPPING:  # stopping already (SLURM and Snakemake may signal twice): let the cleanup finish
        return
    if _HELD:  # a block that must not be cut in half: the stop comes when it ends
        if not _PENDING:
            _PENDING.append(signum)
        return
    _STOPPING.append(signum)
    raise Stopped(signum)


def stopping() -> int | None:
    """The signal that is stopping the command (a :class:`Stopped` has been raised), else None.
    A stop that lands inside a native module's initialisation comes out as that module's
    ``ImportError``; the command's ending asks this to tell it from a broken install."""
    return _STOPPING[0] if _STOPPING else None


def _stop_now(signum, frame) -> None:
    if _HELD:
        if not _PENDING:
            _PENDING.append(signum)
        return
    text, rc = stop_line(Stopped(signum))
    with contextlib.suppress(OSError):
        os.write(2, f"ERROR: {text}\n".encode())
    os._exit(rc)


def stops_early() -> None:
    """From a command's first lines until its :func:`stops_caught` takes over (imports,
    argument parsing): a stop signal ends the process at once with the one line of
    :func:`stop_line` and exit code 128 + the signal. Nothing has been written yet; raising
    inside an import instead would surface as a traceback (a native module's ``ImportError``),
    and Python's own defaults are a ``KeyboardInterrupt`` traceback and a silent death by
    SIGTERM. A signal ignored at start stays ignored; main thread only."""
    if threading.current_thread() is not threading.main_thread():
        return
    for signum in STOP_SIGNALS:
        with contextlib.suppress(ValueError, OSError):
            if signal.getsignal(signum) is not signal.SIG_IGN:
                signal.signal(signum, _stop_now)


def early_if_main() -> None:
    """:func:`stops_early` when the process was started as ``python -m PACKAGE[.module]``, called
    first in each stage package's ``__init__`` (which runs before its ``__main__``): while
    Python locates the ``-m`` module ``sys.argv[0]`` is ``"-m"`` (the interpreter's documented
    behaviour); a library import leaves the signals alone."""
    if sys.argv[:1] == ["-m"]:
        stops_early()


def _install() -> dict:
    """Point every stop signal that is not ignored at :func:`_stop`; returns the handlers replaced."""
    previous = {}
    for signum in STOP_SIGNALS:
        try:
            old = signal.getsignal(signum)
            if old is signal.SIG_IGN:
                continue
            signal.signal(signum, _stop)
            previous[signum] = old
        except (ValueError, OSError):
            pass
    return previous


class _Loader(importlib.abc.Loader):
    """A watched module's own loader; installs the stop handlers again after the module ran."""

    def __init__(self, loader):
        self._loader = loader

    def create_module(self, spec):
        return self._loader.create_module(spec)

    def exec_module(self, module) -> None:
        try:
            self._loader.exec_module(module)
        finally:
            module.__loader__ = self._loader
            if module.__spec__ is not None:
                module.__spec__.loader = self._loader
            if _ACTIVE and threading.current_thread() is threading.main_thread():
                _install()


class _Watch(importlib.abc.MetaPathFinder):
    """Finds a module of :data:`NATIVE_HANDLERS` with the other finders and wraps its loader."""

    def find_spec(self, name, path=None, target=None):
        if name not in NATIVE_HANDLERS:
            return None
        spec = importlib.machinery.PathFinder.find_spec(name, path, target)
        if spec is None or spec.loader is None or not hasattr(spec.loader, "exec_module"):
            return None
        spec.loader = _Loader(spec.loader)
        return spec


@contextlib.contextmanager
def stops_held() -> Iterator[None]:
    """Hold the stop signals back for a short block that must not be cut in half (a temporary
    name being made, a marker or ledger being rewritten); a stop that came meanwhile takes
    effect when the block ends. Python's handlers run in the main thread whichever thread the
    kernel delivered the signal to (torch's and OpenMP's threads included), so the hold is a
    flag that :func:`_stop` reads; the signals are also blocked in this thread for Python's own
    SIGINT handler where :func:`stops_caught` is not active."""
    mask = hasattr(signal, "pthread_sigmask")
    blocked = signal.pthread_sigmask(signal.SIG_BLOCK, STOP_SIGNALS) if mask else None
    _HELD.append(True)
    try:
        yield
    finally:
        _HELD.pop()
        if mask:
            signal.pthread_sigmask(signal.SIG_SETMASK, blocked)  # a blocked signal is handled here
        if not _HELD and _PENDING:
            signal.raise_signal(_PENDING.pop())  # its handler raises Stopped in the main thread


_WATCH = _Watch()
_ACTIVE: list[bool] = []


@contextlib.contextmanager
def stops_caught() -> Iterator[None]:
    """Turn the stop signals into :class:`Stopped` for the block (main thread only; elsewhere
    a no-op), again after a module of :data:`NATIVE_HANDLERS` is imported; the handlers found
    are put back afterwards."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = _install()
    _ACTIVE.append(True)
    if _WATCH not in sys.meta_path:
        sys.meta_path.insert(0, _WATCH)
    try:
        yield
    finally:
        _ACTIVE.pop()
        if not _ACTIVE:
            _STOPPING.clear()
            _PENDING.clear()
            with contextlib.suppress(ValueError):
                sys.meta_path.remove(_WATCH)
        for signum, handler in previous.items():
            with contextlib.suppress(ValueError, OSError, TypeError):
                signal.signal(signum, handler if handler is not None else signal.SIG_DFL)


def run_command(work: Callable[[], int | None], log: logging.Logger | None = None) -> int:
    """The ending of a command that writes no stage output folder (a benchmark runner): ``work``'s
    exit code, or after a stop signal the one line of :func:`stop_line` and 128 + the signal.
    (Stage commands end with ``runtime.outdir.run_stage``, which also tidies their output folder.)"""
    with stops_caught():
        try:
            return int(work() or 0)
        except BaseException as exc:
            if not isinstance(exc, (Stopped, KeyboardInterrupt)) and stopping() is None:
                raise
            text, rc = stop_line(exc if isinstance(exc, (Stopped, KeyboardInterrupt)) else Stopped(stopping()))
            (log or logging.getLogger(__name__)).error("%s", text)
            return rc


def run_child(argv: list[str], **popen) -> int:
    """``subprocess.run(argv, **popen).returncode`` for a child command that may run long: a
    stop of this command is passed on to the child (the same signal), which is waited for
    :data:`CHILD_GRACE_S` so that its own cleanup runs; then the stop goes on here.
    (``subprocess.run`` kills the child at once, leaving its temporary files behind.)"""
    proc = subprocess.Popen(argv, **popen)
    try:
        return proc.wait()
    except (Stopped, KeyboardInterrupt) as exc:
        if proc.poll() is None:
            proc.send_signal(exc.signum if isinstance(exc, Stopped) else signal.SIGINT)
            try:
                proc.wait(timeout=CHILD_GRACE_S)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        raise
