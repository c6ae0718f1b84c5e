"""The initialisers, listed once: name, command, what each writes and needs, how the Bridge reads it.

The workflow reads this list (the ``init`` wildcard, which Bridge rule and which Bridge modes an
initialiser gets, the file that marks its finished run, the scenes it cannot run on), and
tests/test_initialiser_registry.py checks that the config schema's enum and the workflow's
rules agree with it. Adding an initialiser: docs/contracts.md, "Adding an initialiser".

Nothing here imports a stage: a command is named by its module, run as ``python -m``.
"""
from __future__ import annotations

from dataclasses import dataclass

__all__ = ["Initialiser", "INITIALISERS", "NAMES", "NEEDS", "get", "from_predictions", "from_colmap_model"]

#: what an initialiser may need, and the reason the workflow logs when a scene lacks it
#: (``weights`` is the VGGT checkpoint: looked up when the job runs, not at planning)
NEEDS = {
    "weights": "it needs the VGGT-1B checkpoint",
    "reference": "it needs reference cameras and the scene has none",
    "gt_geometry": "it needs ground-truth depth (synthetic scenes only)",
}


@dataclass(frozen=True)
class Initialiser:
    """One initialiser of the workflow.

    Attributes:
        name: the name in configs (``initialisers: [...]``) and result paths (``n{n}/{name}/``).
        command: the module run as ``python -m`` (its docstring and ``--help`` give the flags).
        writes: what its run folder holds (docs/contracts.md has each file's schema).
        marker: the file whose presence marks a finished run (the workflow's target).
        confidence: it writes ``predictions.npz`` with a per-point confidence, which the Bridge
            reads with every configured mode (gated, uniform, filtered); otherwise it writes a
            COLMAP model that the Bridge seeds from in ``uniform`` mode only.
        needs: keys of :data:`NEEDS`.
        base: for a bundle-adjustment step, the initialiser whose cameras it refines.
        gpu: it runs on a GPU when one is configured (``vggt.device``).
    """

    name: str
    command: str
    writes: tuple[str, ...]
    marker: str
    confidence: bool
    needs: frozenset[str] = frozenset()
    base: str | None = None
    gpu: bool = False

    def __post_init__(self) -> None:
        unknown = set(self.needs) - set(NEEDS)
        if unknown:
            raise ValueError(f"initialiser {self.name}: unknown needs {sorted(unknown)}; known: {sorted(NEEDS)}")
        if self.marker not in self.writes:
            raise ValueError(f"initialiser {self.name}: its marker {self.marker} is not among what it writes")


_PREDICTIONS = ("predictions.npz", "sparse/0")
_MODEL = ("sparse/0", "status.json")


def _ba(base: Initialiser) -> Initialiser:
    """The bundle-adjustment step on ``base``: its cameras refined, its seed kept."""
    return Initialiser(f"{base.name}_ba", "evaluation.initialisers.ba_init",
                       (*_PREDICTIONS, "status.json") if base.confidence else _MODEL, "status.json",
                       base.confidence, base.needs, base=base.name)


_VGGT = Initialiser("vggt", "vggt_init", (*_PREDICTIONS, "timing.json"), "timing.json", True,
                    frozenset({"weights"}), gpu=True)
_ORACLE = Initialiser("oracle", "evaluation.initialisers.oracle", (*_PREDICTIONS, "status.json"), "status.json",
                      True, frozenset({"gt_geometry"}))
_POSED = Initialiser("posed", "evaluation.initialisers.posed", _MODEL, "status.json", False,
                     frozenset({"reference"}))

#: every initialiser, by name, in the order tables list them
INITIALISERS: dict[str, Initialiser] = {i.name: i for i in (
    _VGGT,
    Initialiser("colmap", "evaluation.initialisers.colmap_baseline", _MODEL, "status.json", False),
    _ORACLE,
    _POSED,
    _ba(_VGGT),
    _ba(_ORACLE),
    _ba(_POSED),
    Initialiser("random", "evaluation.initialisers.random_init", _MODEL, "status.json", False,
                frozenset({"reference"})),
)}
NAMES = tuple(INITIALISERS)


def get(name: str) -> Initialiser:
    """The initialiser called ``name`` (KeyError naming the known ones otherwise)."""
    try:
        return INITIALISERS[name]
    except KeyError:
        raise KeyError(f"unknown initialiser {name!r}; known: {', '.join(NAMES)}") from None


def from_predictions() -> tuple[str, ...]:
    """Names of the initialisers the Bridge reads from ``predictions.npz`` (every mode)."""
    return tuple(n for n, i in INITIALISERS.items() if i.confidence)


def from_colmap_model() -> tuple[str, ...]:
    """Names of the initialisers the Bridge reads from their COLMAP model (uniform only)."""
    return tuple(n for n, i in INITIALISERS.items() if not i.confidence)
