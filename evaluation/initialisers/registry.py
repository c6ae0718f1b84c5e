"""The initialisers, listed once: name, command, what each writes and needs, how the Bridge reads it.

The workflow reads this list (the config check's ``initialisers`` enum and the config blocks of
the options of an initialiser without a rule of its own, the ``init`` wildcard, the rule that
runs an initialiser, which Bridge rule and which Bridge modes it gets, the file that marks its
finished run, the scenes it cannot run on, the runs whose status decides what follows), and so
do the reports (the order and labels of initialisers, Table I's pair, the study's notes);
tests/test_initialiser_registry.py checks that the workflow's rules agree with it and that
reports and planning spell no initialiser's name.
Adding an initialiser: docs/contracts.md, "Adding an initialiser" (this file and the
initialiser's own module; tests/test_add_initialiser.py proves it).

Nothing here imports a stage: a command is named by its module, run as ``python -m``.
"""
from __future__ import annotations

import re
from dataclasses import dataclass

__all__ = ["Initialiser", "Option", "INITIALISERS", "NAMES", "NEEDS", "COMMON_ARGS", "get", "from_predictions",
           "from_colmap_model", "with_common_rule", "studied", "ba_bases", "dense_bases", "option_blocks",
           "checkpointed", "with_role", "rank", "label", "ROLES"]

#: what an initialiser may need, and the reason the workflow logs when a scene lacks it
#: (``weights`` is the VGGT checkpoint: looked up when the job runs, not at planning)
NEEDS = {
    "weights": "it needs the VGGT-1B checkpoint",
    "reference": "it needs reference cameras and the scene has none",
    "gt_geometry": "it needs ground-truth depth (synthetic scenes only)",
}

#: the roles in Table I (evaluation/reports/tables.py): the method the paper proposes and the
#: baseline it is compared with; one initialiser each
ROLES = ("ours", "baseline")

#: the command line of an initialiser without a rule of its own (``own_rule`` False): the
#: workflow's common rule (workflow/rules/init.smk, ``registry_init``) runs
#: ``python -m COMMAND`` with these flags, then one flag per :class:`Option` of its entry; it
#: writes a COLMAP model and status.json
COMMON_ARGS = "--scene SCENE --image-list TRAIN_TXT --out DIR"

_TYPES = {"integer": int, "number": (int, float), "string": str, "boolean": bool}


@dataclass(frozen=True)
class Option:
    """One option of an initialiser the common rule runs: a key of its config block (the block
    named after the initialiser, ``<name>: {key: value}``), passed to its command as a flag.

    The config check makes the block's schema from these (workflow/scripts/check_config.py), and
    the common rule passes ``--key-with-dashes VALUE`` (a boolean: the bare flag when true).

    Attributes:
        key: the config key (lower case, ``_`` between words).
        type: its JSON-schema type: ``integer``, ``number``, ``string`` or ``boolean``.
        default: the value when the config leaves it out; None: the flag is left out and the
            command's own default holds (the one place of that default).
        help: one line, the config key's description.
        minimum, maximum: the range the command's flag accepts (numbers only).
    """

    key: str
    type: str
    default: object
    help: str
    minimum: float | None = None
    maximum: float | None = None

    def __post_init__(self) -> None:
        if not re.fullmatch(r"[a-z][a-z0-9_]*", self.key):
            raise ValueError(f"option {self.key!r}: a config key is lower case letters, digits and _")
        if self.type not in _TYPES:
            raise ValueError(f"option {self.key}: type {self.type!r} is not one of {', '.join(_TYPES)}")
        ok = _TYPES[self.type]
        if self.default is not None and (not isinstance(self.default, ok)
                                         or (self.type != "boolean" and isinstance(self.default, bool))):
            raise ValueError(f"option {self.key}: default {self.default!r} is not of type {self.type}")
        if (self.minimum is not None or self.maximum is not None) and self.type not in ("integer", "number"):
            raise ValueError(f"option {self.key}: a range needs a number, not {self.type}")

    @property
    def flag(self) -> str:
        """The command's flag: ``--`` and the key with dashes."""
        return "--" + self.key.replace("_", "-")

    def schema(self) -> dict:
        """The JSON schema of the config key (null allowed when the default is None)."""
        out = {"type": self.type if self.default is not None else [self.type, "null"],
               "default": self.default, "description": self.help}
        out.update({k: v for k, v in (("minimum", self.minimum), ("maximum", self.maximum)) if v is not None})
        return out

    def args(self, value) -> list[str]:
        """The command-line words for ``value``: none for None or a false boolean."""
        if value is None or value is False:
            return []
        if value is True:
            return [self.flag]
        return [self.flag, str(value)]


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
        own_rule: workflow/rules/init.smk has a rule of its own for it (its flags come from its
            config block); otherwise the common rule runs it with :data:`COMMON_ARGS`, and it
            writes ``sparse/0`` and ``status.json`` (its marker), with no confidence.
        study: a study cell can degrade it (config ``study.initialiser``): its command takes
            the noise flags ``--rot-deg --trans-frac --depth-rel --outlier-frac``.
        cameras_from: for a dense step (``<base>_mvs``), the initialiser whose COLMAP model
            gives the cameras that multi-view stereo of the training views starts from
            (scenes without reference cameras: your own photos).
        options: what the common rule passes from the initialiser's config block (own rule:
            none here; its block and params function are in the workflow).
        label: its name in tables, plots and the report (default: ``name``).
        role: one of :data:`ROLES` (Table I's columns), or None.
        study_note: for a studied initialiser, what its study cells are (the study report's
            first paragraph).
        checkpoint: its status.json decides what follows its run (its success, registered views,
            alignment, random-point fallback): the workflow plans the stages after it, and the
            dense steps on its cameras, once all such runs have finished (a checkpoint).
    """

    name: str
    command: str
    writes: tuple[str, ...]
    marker: str
    confidence: bool
    needs: frozenset[str] = frozenset()
    base: str | None = None
    gpu: bool = False
    own_rule: bool = False
    study: bool = False
    cameras_from: str | None = None
    options: tuple[Option, ...] = ()
    label: str = ""
    role: str | None = None
    checkpoint: bool = False
    study_note: str = ""

    def __post_init__(self) -> None:
        if not self.label:
            object.__setattr__(self, "label", self.name)
        if self.options and self.own_rule:
            raise ValueError(f"initialiser {self.name}: options are for the common rule; a rule of its own "
                             "takes its flags from its params function")
        if self.role is not None and self.role not in ROLES:
            raise ValueError(f"initialiser {self.name}: role {self.role!r} is not one of {', '.join(ROLES)}")
        keys = [o.key for o in self.options]
        if len(set(keys)) != len(keys):
            raise ValueError(f"initialiser {self.name}: an option key is given twice ({', '.join(keys)})")
        unknown = set(self.needs) - set(NEEDS)
        if unknown:
            raise ValueError(f"initialiser {self.name}: unknown needs {sorted(unknown)}; known: {sorted(NEEDS)}")
        if self.marker not in self.writes:
            raise ValueError(f"initialiser {self.name}: its marker {self.marker} is not among what it writes")
        if not self.own_rule and (self.writes != _MODEL or self.marker != "status.json" or self.confidence
                                  or self.base or self.gpu):
            raise ValueError(f"initialiser {self.name}: the common rule runs a CPU command that writes "
                             f"{' and '.join(_MODEL)} (marker status.json, no confidence, no base); "
                             "anything else needs own_rule=True and its rule in workflow/rules/init.smk")


_PREDICTIONS = ("predictions.npz", "sparse/0")
_MODEL = ("sparse/0", "status.json")


def _ba(base: Initialiser) -> Initialiser:
    """The bundle-adjustment step on ``base``: its cameras refined, its seed kept."""
    return Initialiser(f"{base.name}_ba", "evaluation.initialisers.ba_init",
                       (*_PREDICTIONS, "status.json") if base.confidence else _MODEL, "status.json",
                       base.confidence, base.needs, base=base.name, own_rule=True)


_VGGT = Initialiser("vggt", "vggt_init", (*_PREDICTIONS, "timing.json"), "timing.json", True,
                    frozenset({"weights"}), gpu=True, own_rule=True, role="ours")
_ORACLE = Initialiser(
    "oracle", "evaluation.initialisers.oracle", (*_PREDICTIONS, "status.json"), "status.json", True,
    frozenset({"gt_geometry"}), own_rule=True, study=True,
    study_note="Every cell is the oracle (ground truth with seeded noise), never VGGT. Named operating points "
               "ending in `_sim` are simulations of VGGT-like error (pose noise calibrated to the ATE and rotation "
               "errors the paper reports for VGGT), not VGGT output.")
_POSED = Initialiser(
    "posed", "evaluation.initialisers.posed", _MODEL, "status.json", False, frozenset({"reference"}),
    own_rule=True, study=True,
    study_note="Every cell is the posed initialiser (the scene's reference cameras, estimated from all of its "
               "images, and points triangulated with them; evaluation/initialisers/posed.py) with the oracle's "
               "seeded noise, never VGGT. It has no confidence: Bridge mode uniform only; no floater measure "
               "without a ground-truth mesh.")
_MVS = Initialiser("mvs", "evaluation.initialisers.mvs", (*_PREDICTIONS, "status.json"), "status.json", True,
                   frozenset({"reference"}), own_rule=True)
_COLMAP = Initialiser("colmap", "evaluation.initialisers.colmap_baseline", _MODEL, "status.json", False,
                      own_rule=True, role="baseline", checkpoint=True)


def _dense(base: Initialiser) -> Initialiser:
    """Multi-view stereo of the training views on ``base``'s cameras: dense points with a
    confidence where the scene has no reference cameras."""
    return Initialiser(f"{base.name}_mvs", _MVS.command, _MVS.writes, "status.json", True, base.needs,
                       own_rule=True, cameras_from=base.name)

#: every initialiser, by name, in the order tables list them
INITIALISERS: dict[str, Initialiser] = {i.name: i for i in (
    _VGGT,
    _COLMAP,
    _ORACLE,
    _POSED,
    _MVS,
    _ba(_VGGT),
    _ba(_ORACLE),
    _ba(_POSED),
    Initialiser("random", "evaluation.initialisers.random_init", _MODEL, "status.json", False,
                frozenset({"reference"}), own_rule=True),
    _dense(_VGGT),
    _dense(_COLMAP),
)}
NAMES = tuple(INITIALISERS)
if any(sum(i.role == r for i in INITIALISERS.values()) != 1 for r in ROLES):
    raise ValueError(f"each role ({', '.join(ROLES)}) is one initialiser's")


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


def with_common_rule() -> tuple[str, ...]:
    """Names of the initialisers the workflow's common rule runs (no rule of their own)."""
    return tuple(n for n, i in INITIALISERS.items() if not i.own_rule)


def studied() -> tuple[str, ...]:
    """Names of the initialisers a study cell can degrade (config ``study.initialiser``)."""
    return tuple(n for n, i in INITIALISERS.items() if i.study)


def ba_bases(confidence: bool) -> tuple[str, ...]:
    """Names of the initialisers a bundle-adjustment step refines, with (or without) a confidence."""
    return tuple(i.base for i in INITIALISERS.values() if i.base and i.confidence == confidence)


def dense_bases() -> tuple[str, ...]:
    """Names of the initialisers whose cameras a dense step (``<base>_mvs``) starts from."""
    return tuple(i.cameras_from for i in INITIALISERS.values() if i.cameras_from)


def option_blocks() -> dict[str, dict]:
    """The config schema's block of each initialiser the common rule runs with options:
    ``{name: JSON schema of {key: value}}`` (each key's default filled in when left out)."""
    return {n: {"type": "object", "additionalProperties": False, "default": {},
                "description": f"options of the {n} initialiser (python -m {i.command}; "
                               "evaluation/initialisers/registry.py)",
                "properties": {o.key: o.schema() for o in i.options}}
            for n, i in INITIALISERS.items() if i.options}


def checkpointed() -> tuple[str, ...]:
    """Names of the initialisers whose status.json decides what follows (``checkpoint``)."""
    return tuple(n for n, i in INITIALISERS.items() if i.checkpoint)


def with_role(role: str) -> str:
    """The name of the initialiser with ``role`` (one of :data:`ROLES`)."""
    return next(n for n, i in INITIALISERS.items() if i.role == role)


def rank(name: str) -> int:
    """Where ``name`` comes in tables and the report: its place in the registry; a name the
    registry does not know (a results tree from elsewhere) after all of them."""
    return NAMES.index(name) if name in INITIALISERS else len(NAMES)


def label(name: str) -> str:
    """The name tables and the report show for ``name`` (its ``label``; an unknown name as is)."""
    return INITIALISERS[name].label if name in INITIALISERS else name
