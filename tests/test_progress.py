"""Progress that never seems to go backwards: when snakemake's total grows after the COLMAP
checkpoint, a line counts the new jobs into the total (workflow/scripts/progress.py, which
scripts/demo.sh and scripts/photos.py pipe snakemake's output through)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

LOG = """[Fri Nov 27 06:00:00 2026]
Finished jobid: 12 (Rule: colmap_index)
27 of 31 steps (87%) done
Updating checkpoint dependencies.
[Fri Nov 27 06:00:05 2026]
Finished jobid: 14 (Rule: pose_eval)
28 of 47 steps (60%) done
29 of 47 steps (62%) done
"""


def test_a_growing_total_is_said_in_words():
    proc = subprocess.run([sys.executable, str(ROOT / "workflow" / "scripts" / "progress.py"), "--prefix", "[demo]"],
                          input=LOG, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    out = proc.stdout.splitlines()
    added = [ln for ln in out if ln not in LOG.splitlines()]
    assert added == ["[demo] 16 new job(s) planned now that the runs they depend on (the COLMAP checkpoint) have "
                     "finished: 27 of 31 done so far, 47 steps in all now"]
    assert out.index(added[0]) == out.index("28 of 47 steps (60%) done") - 1
    assert [ln for ln in out if ln != added[0]] == LOG.splitlines()  # everything else unchanged
