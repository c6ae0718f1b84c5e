"""What the viewer serves as ``/model.<type>``: the bytes of one checked model, followed live.

A model is a 3DGS PLY, an antimatter15 ``.splat`` or a Niantic ``.spz`` (what
``python -m splat_train export`` writes); its type is its file's suffix (:func:`model_type`),
and the page tells Spark which it is. The model file is read once into memory and exactly those
bytes are checked by the reader of its type (:func:`check_model`: :func:`camio.ply.read_gaussian_ply`,
:func:`camio.splatfmt.read_splat`, :func:`camio.splatfmt.read_spz`) and served; the file is
never opened again to answer a request, so a file swapped after the check is not served
unchecked. Every :data:`FOLLOW_POLL_S` the viewer looks at the file again (its inode, size and
modification time); when it changed, the new bytes are read and checked the same way and served
from then on, with a new ``version``; bytes that are not a model of that type are not served
(the last good model stays, and one warning names the file).

``--model`` may name a training run's output folder: the viewer then follows its
``snapshot.ply`` (written by ``--snapshot-every``, :mod:`splat_train.training.snapshot`), or its
``model.ply`` while there is no snapshot; before either exists ``/model.ply`` answers 503 and
the page waits. The iteration in a snapshot's header is served beside the bytes.
"""

from __future__ import annotations

import json
import logging
import os
import threading
from dataclasses import dataclass
from pathlib import Path

from camio.ply import read_gaussian_ply
from camio.splatfmt import EXPORT_FORMATS, read_splat, read_spz
from splat_train.training.snapshot import SNAPSHOT_FILE, snapshot_iteration

log = logging.getLogger("splat_train.view")

FOLLOW_POLL_S = 1.0  # seconds between two looks at the model file
MODEL_FILE = "model.ply"  # a finished run's model (docs/contracts.md, splat_train output)
#: the model types the viewer shows, by file suffix (Spark's ``fileType``): those export writes
MODEL_TYPES = EXPORT_FORMATS
#: what each type is called in a message
TYPE_NAMES = {"ply": "3DGS PLY", "splat": ".splat file", "spz": ".spz file"}


class UnknownModelType(ValueError):
    """A model file whose suffix is none of :data:`MODEL_TYPES`."""


def model_type(path: str | Path) -> str:
    """The type of the model file ``path`` from its suffix (any case): one of :data:`MODEL_TYPES`.

    Raises:
        UnknownModelType: any other suffix (the message lists the ones shown).
    """
    kind = Path(path).suffix.lower().lstrip(".")
    if kind not in MODEL_TYPES:
        raise UnknownModelType(f"{path}: the viewer shows {', '.join('.' + t for t in MODEL_TYPES)} files "
                               f"(what `python -m splat_train export` writes) or a training run's folder; "
                               f"not {Path(path).suffix or 'a file without a suffix'}")
    return kind


def check_model(path: str | Path, data: bytes, kind: str) -> None:
    """Check that ``data`` (the bytes of ``path``) is a model of type ``kind`` (:data:`MODEL_TYPES`).

    Raises:
        PlyFormatError, SplatFormatError (both ValueError): it is not; SpzUnavailable (a
        SplatFormatError) for ``.spz`` without the gsply package.
    """
    {"ply": read_gaussian_ply, "splat": read_splat, "spz": read_spz}[kind](path, data)


def read_checked(path: str | Path) -> bytes:
    """The bytes of the 3DGS PLY ``path``, read once and checked (what the viewer serves for a
    file that is not followed: the seed). PlyFormatError / OSError otherwise."""
    data = Path(path).read_bytes()
    check_model(path, data, "ply")
    return data


@dataclass(frozen=True)
class Served:
    """One checked model: its bytes, file, training iteration (None for a PLY without one)
    and ``version`` (1 for the first model served, +1 for each change taken)."""

    data: bytes
    path: Path
    iteration: int | None
    version: int


class ModelSource:
    """The model ``target`` names (a model file, or a training run's folder: module docstring).
    UnknownModelType for a file whose suffix is not a model type."""

    def __init__(self, target: str | Path) -> None:
        self.target = Path(target)
        self.folder = self.target.is_dir()
        self.kind = "ply" if self.folder else model_type(self.target)  # a run's folder holds PLYs
        self._lock = threading.Lock()
        self._served: Served | None = None
        self._seen: tuple | None = None  # the file state last read, good or not

    def candidates(self) -> list[Path]:
        """The files to serve, the first that exists wins."""
        return [self.target / SNAPSHOT_FILE, self.target / MODEL_FILE] if self.folder else [self.target]

    def current(self) -> Served | None:
        """The model served now (None before the first good one)."""
        with self._lock:
            return self._served

    def refresh(self, strict: bool = False) -> bool:
        """Look at the file once; take its bytes when it changed and they are a model of its type.

        Returns:
            Whether a new model is served from now on.

        Raises:
            PlyFormatError, SplatFormatError, ValueError, OSError: with ``strict`` (the start), a
            file that cannot be read or is not a model of its type. Without, these are a warning
            (once per change of the file) and the last good model stays.
        """
        path = next((p for p in self.candidates() if p.exists()), None)
        if path is None:
            if strict and not self.folder:
                raise FileNotFoundError(f"{self.target}: no such file")
            return False
        try:
            with open(path, "rb") as f:
                st = os.fstat(f.fileno())
                key = (str(path), st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns)
                if key == self._seen:
                    return False
                data = f.read()
        except OSError as e:
            if strict:
                raise
            log.debug("cannot read %s now: %s", path, e)  # e.g. removed between the look and the read
            return False
        self._seen = key
        try:
            check_model(path, data, self.kind)  # the very bytes that will be served
        except ValueError as e:  # PlyFormatError and SplatFormatError are ValueErrors
            if strict:
                raise
            log.warning("%s changed but is not a %s (%s); still serving the last good model", path,
                        TYPE_NAMES[self.kind], e)
            return False
        it = snapshot_iteration(data[:4096]) if self.kind == "ply" else None
        with self._lock:
            version = (self._served.version + 1) if self._served else 1
            self._served = Served(data, path, it, version)
        # the start's model is named on the command's own first line; a later one gets its line here
        log.log(logging.DEBUG if strict else logging.INFO, "serving %s%s (version %d)", path,
                "" if it is None else f" at iteration {it}", version)
        return True

    def state(self) -> dict:
        """``/state.json``: what the page polls to know when to load the model again, and the
        model's ``type`` (:data:`MODEL_TYPES`: Spark's ``fileType``, the suffix of ``/model.<type>``)."""
        s = self.current()
        return {"version": 0 if s is None else s.version, "iteration": None if s is None else s.iteration,
                "file": None if s is None else s.path.name, "type": self.kind, "follow": True}

    def state_json(self) -> bytes:
        return json.dumps(self.state()).encode()


def follow(source: ModelSource, stop: threading.Event, poll_s: float = FOLLOW_POLL_S) -> threading.Thread:
    """A daemon thread calling ``source.refresh()`` every ``poll_s`` seconds until ``stop`` is set."""
    def loop() -> None:
        while not stop.wait(poll_s):
            try:
                source.refresh()
            except Exception as e:  # never let the watcher die silently: say it, keep serving
                log.warning("cannot look at %s: %s", source.target, e)

    t = threading.Thread(target=loop, name="view-follow", daemon=True)
    t.start()
    return t
