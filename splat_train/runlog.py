"""The per-iteration training record, written as ``DIR/log.parquet`` (docs/contracts.md).

Columns: ``iteration`` (int64, 1-based), ``wall_time_s`` (training time so far, excluding
held-out evaluation and checkpoint writing; continued across resumes), ``loss``, ``l1``,
``ssim`` (of the training view of that iteration), ``train_psnr`` (PSNR of that view),
``num_gaussians`` (int64, after that iteration's densification), ``test_psnr`` (mean
held-out PSNR, null except at evaluation iterations). The (wall_time_s, test_psnr) pairs are
the error-against-run-time record.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch

from camio.atomic import atomic_path

__all__ = ["RunLog", "LOG_COLUMNS"]

LOG_COLUMNS = ("iteration", "wall_time_s", "loss", "l1", "ssim", "train_psnr", "num_gaussians", "test_psnr")
_INT_COLUMNS = ("iteration", "num_gaussians")


class RunLog:
    """Rows of :data:`LOG_COLUMNS`, kept in memory and checkpointed as float64 tensors."""

    def __init__(self) -> None:
        self.rows: dict[str, list[float]] = {c: [] for c in LOG_COLUMNS}

    def __len__(self) -> int:
        return len(self.rows["iteration"])

    def append(self, **values: float) -> None:
        missing = set(LOG_COLUMNS) - set(values)
        if missing:
            raise ValueError(f"log row lacks {sorted(missing)}")
        for c in LOG_COLUMNS:
            self.rows[c].append(float(values[c]))

    def set_last(self, column: str, value: float) -> None:
        self.rows[column][-1] = float(value)

    def test_curve(self) -> dict[str, Any]:
        """The held-out PSNR curve: ``{"iterations": [...], "test_psnr": [...], "best_iteration",
        "best_test_psnr", "last_iteration", "last_test_psnr"}`` over the rows that have one (in a
        sparse-view run held-out PSNR can peak early, so the best is kept beside the last);
        empty lists and None when no row does."""
        pairs = [(int(i), p) for i, p in zip(self.rows["iteration"], self.rows["test_psnr"]) if np.isfinite(p)]
        best = max(pairs, key=lambda x: x[1]) if pairs else (None, None)
        return {"iterations": [i for i, _ in pairs], "test_psnr": [p for _, p in pairs],
                "best_iteration": best[0], "best_test_psnr": best[1],
                "last_iteration": pairs[-1][0] if pairs else None, "last_test_psnr": pairs[-1][1] if pairs else None}

    def state_dict(self) -> dict[str, torch.Tensor]:
        return {c: torch.tensor(v, dtype=torch.float64) for c, v in self.rows.items()}

    def load_state_dict(self, state: dict[str, torch.Tensor]) -> None:
        self.rows = {c: [float(x) for x in state[c].tolist()] for c in LOG_COLUMNS}

    def write_parquet(self, path: str | Path) -> Path:
        """Write the rows atomically; NaN test_psnr becomes null."""
        import pyarrow as pa
        import pyarrow.parquet as pq

        cols = {}
        for c in LOG_COLUMNS:
            a = np.asarray(self.rows[c], dtype=np.float64)
            if c in _INT_COLUMNS:
                cols[c] = pa.array(a.astype(np.int64))
            else:
                cols[c] = pa.array(a, mask=~np.isfinite(a) if c == "test_psnr" else None)
        with atomic_path(path) as tmp:
            pq.write_table(pa.table(cols), tmp)
        return Path(path)
