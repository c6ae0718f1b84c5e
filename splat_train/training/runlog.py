"""The per-iteration training record, written as ``DIR/log.parquet`` (docs/contracts.md).

Columns: ``iteration`` (int64, 1-based), ``wall_time_s`` (training time so far, excluding
held-out evaluation and checkpoint writing; continued across resumes; on a GPU exact at the
rows where the trainer synchronises: every ``trainer.SYNC_EVERY``-th, evaluation, log and
checkpoint rows, and between them the host's time so far), ``loss``, ``l1``,
``ssim`` (of the training view of that iteration), ``train_psnr`` (PSNR of that view),
``num_gaussians`` (int64, after that iteration's densification), and the held-out means over
the test views at evaluation iterations (null elsewhere): ``test_psnr`` (dB), ``test_ssim``
(3DGS SSIM, :func:`splat_train.losses.ssim`) and ``test_lpips`` (LPIPS v0.1, AlexNet; null
also when LPIPS along the run is off, ``TrainConfig.eval_lpips``, or its weights are absent),
and two diagnostics of where the held-out error is (:mod:`splat_train.training.heldout`):
``test_coverage`` (the share of held-out pixels the model covers, accumulated opacity >= 0.5)
and ``test_psnr_covered`` (PSNR over those pixels; null where a view covers none).
They are computed on the float renders clamped to [0, 1], not on the 8-bit PNGs that
``python -m evaluation images`` scores at the end. The (wall_time_s, test_*) pairs are the
error-against-run-time record.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch

from runtime.atomic import atomic_path

__all__ = ["RunLog", "LOG_COLUMNS", "TEST_MEASURES", "TEST_DIAGNOSTICS"]

#: held-out measures: (column, higher is better); null except at evaluation iterations
TEST_MEASURES = (("test_psnr", True), ("test_ssim", True), ("test_lpips", False))
#: held-out diagnostics, no best or worst: the covered share and PSNR, SSIM, LPIPS where covered
TEST_DIAGNOSTICS = ("test_coverage", "test_psnr_covered", "test_ssim_covered", "test_lpips_covered")
LOG_COLUMNS = ("iteration", "wall_time_s", "loss", "l1", "ssim", "train_psnr", "num_gaussians",
               *(c for c, _ in TEST_MEASURES), *TEST_DIAGNOSTICS)
_INT_COLUMNS = ("iteration", "num_gaussians")
_TEST_COLUMNS = (*(c for c, _ in TEST_MEASURES), *TEST_DIAGNOSTICS)


class RunLog:
    """Rows of :data:`LOG_COLUMNS`, kept in memory and checkpointed as float64 tensors."""

    def __init__(self) -> None:
        self.rows: dict[str, list[float]] = {c: [] for c in LOG_COLUMNS}

    def __len__(self) -> int:
        return len(self.rows["iteration"])

    def append(self, **values: float) -> None:
        """One row; the held-out columns may be left out (NaN: no evaluation at this row)."""
        values = {**{c: float("nan") for c in _TEST_COLUMNS}, **values}
        missing = set(LOG_COLUMNS) - set(values)
        if missing:
            raise ValueError(f"log row lacks {sorted(missing)}")
        for c in LOG_COLUMNS:
            self.rows[c].append(float(values[c]))

    def test_curve(self) -> dict[str, Any]:
        """The held-out curves over the evaluation rows (those with a finite ``test_psnr``):
        ``iterations``, ``wall_time_s``, ``test_psnr``, ``test_ssim``, ``test_lpips``,
        ``test_coverage``, ``test_psnr_covered``, ``test_ssim_covered``, ``test_lpips_covered`` (lists of one length; None where a value is
        null, e.g. LPIPS off) and, per measure (not the two diagnostics), the best
        (highest PSNR / SSIM, lowest LPIPS) and the last: ``best_iteration`` /
        ``best_test_psnr`` (PSNR), ``best_ssim_iteration`` / ``best_test_ssim``,
        ``best_lpips_iteration`` / ``best_test_lpips``, ``last_iteration``, ``last_test_psnr``,
        ``last_test_ssim``, ``last_test_lpips``. In a sparse-view run the held-out error can be
        lowest early, so the best is kept beside the last; empty lists and None without rows."""
        rows = [k for k, p in enumerate(self.rows["test_psnr"]) if np.isfinite(p)]
        col = lambda c: [self.rows[c][k] if np.isfinite(self.rows[c][k]) else None for k in rows]  # noqa: E731
        out: dict[str, Any] = {"iterations": [int(self.rows["iteration"][k]) for k in rows],
                               "wall_time_s": col("wall_time_s")}
        for c in _TEST_COLUMNS:
            out[c] = col(c)
        for c, higher in TEST_MEASURES:
            pairs = [(i, v) for i, v in zip(out["iterations"], out[c]) if v is not None]
            best = ((max if higher else min)(pairs, key=lambda x: x[1]) if pairs else (None, None))
            short = c.removeprefix("test_")
            out["best_iteration" if short == "psnr" else f"best_{short}_iteration"] = best[0]
            out[f"best_{c}"] = best[1]
        out["last_iteration"] = out["iterations"][-1] if rows else None
        for c in _TEST_COLUMNS:
            out[f"last_{c}"] = out[c][-1] if rows else None
        return out

    def state_dict(self) -> dict[str, torch.Tensor]:
        return {c: torch.tensor(v, dtype=torch.float64) for c, v in self.rows.items()}

    def load_state_dict(self, state: dict[str, torch.Tensor]) -> None:
        """Rows of a checkpoint; held-out columns a checkpoint predates are filled with NaN."""
        n = len(state["iteration"])
        self.rows = {c: ([float(x) for x in state[c].tolist()] if c in state else [float("nan")] * n)
                     for c in LOG_COLUMNS}

    def write_parquet(self, path: str | Path) -> Path:
        """Write the rows atomically; NaN in the held-out columns becomes null."""
        import pyarrow as pa
        import pyarrow.parquet as pq

        cols = {}
        for c in LOG_COLUMNS:
            a = np.asarray(self.rows[c], dtype=np.float64)
            if c in _INT_COLUMNS:
                cols[c] = pa.array(a.astype(np.int64))
            else:
                cols[c] = pa.array(a, mask=~np.isfinite(a) if c in _TEST_COLUMNS else None)
        with atomic_path(path) as tmp:
            pq.write_table(pa.table(cols), tmp)
        return Path(path)
