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


RUN = """Assuming unrestricted shared filesystem usage.
Building DAG of jobs...
Job stats:
job                 count
----------------  -------
convert_scene           1
total                   2
[Mon Dec  7 08:24:30 2026]
localrule convert_scene:
    input: /tmp/photos
    jobid: 3
VGGT skipped: no checkpoint (offline)
[Mon Dec  7 08:24:31 2026]
Finished jobid: 3 (Rule: convert_scene)
1 of 2 steps (50%) done
Error in rule train_splats:
    log: /tmp/out/train.log (check log file(s) for error details)
"""


def test_brief_keeps_progress_messages_and_errors_only():
    """--brief (scripts/photos.py without -v): no job blocks or banner; each progress line names
    the rule that finished; the workflow's own lines and everything from an error on stay."""
    proc = subprocess.run([sys.executable, str(ROOT / "workflow" / "scripts" / "progress.py"), "--brief"],
                          input=RUN, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.splitlines() == [
        "VGGT skipped: no checkpoint (offline)",
        "1 of 2 steps (50%) done (convert_scene)",
        "Error in rule train_splats:",
        "    log: /tmp/out/train.log (check log file(s) for error details)",
    ]


def test_heartbeat_says_the_time_and_the_newest_log_line(tmp_path):
    """--heartbeat RESULTS: while the input is quiet (a long COLMAP step), a line every
    PROGRESS_HEARTBEAT_S seconds with the time elapsed and the newest job log's last line."""
    import os
    import time

    (tmp_path / "logs").mkdir()
    (tmp_path / "logs" / "old.log").write_text("from an earlier run\n")
    time.sleep(0.05)
    proc = subprocess.Popen([sys.executable, str(ROOT / "workflow" / "scripts" / "progress.py"), "--prefix", "[t]",
                             "--heartbeat", str(tmp_path)], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True,
                            env={**os.environ, "PROGRESS_HEARTBEAT_S": "0.5"})
    time.sleep(0.2)
    (tmp_path / "logs" / "colmap.log").write_text("08:00 INFO matching\n08:01 INFO incremental mapping\n\n")
    time.sleep(1.6)
    out, _ = proc.communicate("1 of 2 steps (50%) done\n", timeout=60)
    beats = [ln for ln in out.splitlines() if ln.startswith("[t] ")]
    assert len(beats) >= 2, out
    assert beats[0] == "[t] 0m00s elapsed; newest log logs/colmap.log: 08:01 INFO incremental mapping", out
    assert out.splitlines()[-1] == "1 of 2 steps (50%) done"
