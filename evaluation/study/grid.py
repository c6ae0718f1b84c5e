"""The initialisation study's grid: the ``study:`` config section -> named oracle noise cells.

A cell is one complete noise setting of the oracle (:class:`evaluation.initialisers.oracle.OracleNoise`
plus ``conf_mode``), named so that it can be a folder and a Snakemake wildcard:

* ``zero``: every noise level 0 (exact ground truth, ``conf_mode`` ranked);
* each entry of ``points`` (e.g. ``vggt_like_sim``): a named operating point, its keys over
  ``zero``;
* for each entry of ``axes`` ({param, levels, base}): one cell per level, named
  ``{param}-{level}``, the base cell (default ``zero``) with that one parameter changed. The
  base is the axis's reference level (level 0 of a numeric axis on ``zero``).

Cells whose settings equal an earlier cell's are dropped (the earlier name is kept), so an
axis level that equals its base costs nothing. Seeds are a separate dimension (``seeds``).
"""

from __future__ import annotations

from evaluation.initialisers.oracle import CONF_MODES

__all__ = ["NOISE_KEYS", "ZERO", "expand_cells", "cell_name"]

NOISE_KEYS = ("rot_deg", "trans_frac", "depth_rel", "outlier_frac", "conf_noise", "conf_mode")
ZERO = {"rot_deg": 0.0, "trans_frac": 0.0, "depth_rel": 0.0, "outlier_frac": 0.0,
        "conf_noise": 0.0, "conf_mode": "ranked"}


def cell_name(param: str, level) -> str:
    """Folder-safe name of an axis cell: ``rot_deg-2``, ``depth_rel-0.05``, ``conf_mode-anti``."""
    if isinstance(level, float) and level.is_integer():
        level = int(level)
    return f"{param}-{level}"


def _setting(base: dict, changes: dict, where: str) -> dict:
    unknown = set(changes) - set(NOISE_KEYS)
    if unknown:
        raise ValueError(f"{where}: unknown noise keys {sorted(unknown)} (allowed: {NOISE_KEYS})")
    out = {**base, **changes}
    if out["conf_mode"] not in CONF_MODES:
        raise ValueError(f"{where}: conf_mode must be one of {CONF_MODES}, got {out['conf_mode']!r}")
    for k in NOISE_KEYS[:-1]:
        out[k] = float(out[k])
    return out


def expand_cells(study: dict) -> dict[str, dict]:
    """The cells of a ``study:`` section, in order: name -> {"noise": full setting, "axis":
    param or None, "level", "base": base cell name or None}.

    Args:
        study: {"points": {name: {noise key: value}}, "axes": [{"param", "levels", "base"}]}.
    """
    cells: dict[str, dict] = {"zero": {"noise": dict(ZERO), "axis": None, "level": None,
                                       "base": None}}
    for name, changes in (study.get("points") or {}).items():
        cells[name] = {"noise": _setting(ZERO, changes, f"study.points.{name}"), "axis": None,
                       "level": None, "base": "zero"}
    for i, axis in enumerate(study.get("axes") or []):
        param, base = axis["param"], axis.get("base", "zero")
        if param not in NOISE_KEYS:
            raise ValueError(f"study.axes[{i}]: param {param!r} is not one of {NOISE_KEYS}")
        if base not in cells:
            raise ValueError(f"study.axes[{i}]: base {base!r} is not a cell ({sorted(cells)})")
        for level in axis["levels"]:
            name = cell_name(param, level)
            cells[name] = {"noise": _setting(cells[base]["noise"], {param: level},
                                             f"study.axes[{i}]"),
                           "axis": param, "level": level, "base": base}
    out, seen = {}, {}
    for name, cell in cells.items():
        key = tuple(sorted(cell["noise"].items()))
        if key in seen:  # same setting as an earlier cell: keep the earlier name
            continue
        seen[key] = name
        out[name] = cell
    return out
