"""experiments/pose_refinement.py --quick on the synthetic scene (one seed): both camera refinements
lower both pose errors from the VGGT-level noise, and the JSON and the table say so."""

from __future__ import annotations

import json

import pytest


@pytest.mark.slow
def test_quick_synthetic_both_methods_lower_both_errors(tmp_path, capsys):
    from experiments import pose_refinement

    assert pose_refinement.main(["--quick", "--scenes", "synthetic", "--seeds", "0", "--out", str(tmp_path)]) == 0
    text = capsys.readouterr().out
    assert "after bundle adjustment" in text and "after training refinement" in text
    (path,) = tmp_path.glob("pose_refinement_*_quick.json")
    row = json.loads(path.read_text())["results"]["synthetic"][0]
    before = row["before"]
    assert 2.0 < before["ate_pct_radius"] < 5.0 and 0.8 < before["rel_rot_deg"] < 2.0  # VGGT's level
    for after in (row["after_ba"], row["posed+refine"]):
        assert after["ate_pct_radius"] < before["ate_pct_radius"]
        assert after["rel_rot_deg"] < before["rel_rot_deg"]
    assert row["ba_fallback"] is None
    for run in ("posed", "posed+refine", "posed_ba", "posed_ba+refine"):
        assert row[run]["psnr"] > 10
