"""The live snapshot of a training run: ``OUT/snapshot.ply`` (docs/contracts.md).

With ``--snapshot-every N`` the trainer writes the model every N iterations (and at the last)
to one file, replaced atomically each time (:func:`camio.ply.write_gaussian_ply` writes beside
it and renames), so a reader sees a whole earlier snapshot or a whole later one, never a mix.
The iteration travels inside the same file, as the header line ``comment iteration N``: the
model and its iteration cannot disagree. ``python -m splat_train view --model OUT`` follows it.
"""

from __future__ import annotations

from pathlib import Path

from camio.ply import GaussianCloud, ply_comments, write_gaussian_ply

__all__ = ["SNAPSHOT_FILE", "write_snapshot", "snapshot_iteration", "check_snapshot_every"]

SNAPSHOT_FILE = "snapshot.ply"
_KEY = "iteration"


def check_snapshot_every(every: int | None) -> int | None:
    """``every`` when it is a snapshot period (None: off, or an integer >= 1); ValueError
    naming ``--snapshot-every`` otherwise."""
    if every is not None and (isinstance(every, bool) or not isinstance(every, int) or every < 1):
        raise ValueError(f"--snapshot-every {every!r}: give a number of iterations >= 1 (or leave it out: "
                         "no snapshots)")
    return every


def write_snapshot(out_dir: str | Path, cloud: GaussianCloud, iteration: int) -> Path:
    """Replace ``out_dir/snapshot.ply`` with ``cloud`` (3DGS layout) at ``iteration``, atomically."""
    return write_gaussian_ply(Path(out_dir) / SNAPSHOT_FILE, cloud, comments=(f"{_KEY} {int(iteration)}",))


def snapshot_iteration(raw: bytes) -> int | None:
    """The training iteration a PLY's header names (``comment iteration N``; ``raw``: the
    file's bytes or its start); None for a PLY without one (a finished ``model.ply``)."""
    for c in ply_comments(raw):
        key, _, value = c.partition(" ")
        if key == _KEY and value.strip().isdigit():
            return int(value)
    return None
