"""Train/test splits and the split manifest ``split.json``.

Rule "every8": sort the image names; test = names[i] with i % 8 == 0; the training pool is
the rest (sorted); the n training views are ``pool[round(linspace(0, len(pool) - 1, n))]``.

Rounding is numpy's ``np.round`` (round half to even), exactly what the seed code's
``np.round(np.linspace(...)).astype(int)`` does; e.g. 13 pool images, n = 9 gives
linspace = 0, 1.5, 3, ..., 12 -> 0, 2, 3, 4, 6, 8, 9, 10, 12 (1.5 -> 2, 4.5 -> 4, 7.5 -> 8,
10.5 -> 10). A manifest (JSON, see :func:`load_manifest`) overrides the rule.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from runtime.atomic import write_json
from runtime.checks import file_problem

__all__ = ["Split", "every8_split", "select_train", "make_split", "load_manifest", "write_split",
           "read_split", "TEST_EVERY"]

TEST_EVERY = 8


@dataclass
class Split:
    """A split of a scene's images.

    Attributes:
        rule: "every8", "manifest" or "fixed".
        test: test image names (sorted).
        train_pool: names the training views are drawn from (sorted).
        train: n (as str) -> training names for that n.
    """

    rule: str
    test: list[str]
    train_pool: list[str]
    train: dict[str, list[str]] = field(default_factory=dict)

    def to_json(self) -> dict:
        return {"rule": self.rule, "test": list(self.test), "train_pool": list(self.train_pool),
                "train": {str(k): list(v) for k, v in self.train.items()}}


def every8_split(names: list[str], every: int = TEST_EVERY) -> tuple[list[str], list[str]]:
    """(test, pool): sorted names, test = index % every == 0, pool = the rest."""
    s = sorted(names)
    if len(set(s)) != len(s):
        raise ValueError("duplicate image names")
    test = [n for i, n in enumerate(s) if i % every == 0]
    pool = [n for i, n in enumerate(s) if i % every != 0]
    return test, pool


def select_train(pool: list[str], n: int) -> list[str]:
    """The n training views: ``pool[np.round(np.linspace(0, len(pool) - 1, n)).astype(int)]``.

    Raises:
        ValueError: n < 1 or n > len(pool).
    """
    n = int(n)
    if n < 1:
        raise ValueError(f"number of training views must be >= 1, got {n}")
    if n > len(pool):
        raise ValueError(f"{n} training views requested but the training pool holds only "
                         f"{len(pool)} images; use a smaller n or a scene with more images")
    idx = np.round(np.linspace(0, len(pool) - 1, n)).astype(int)
    return [pool[i] for i in idx]


def load_manifest(path: str | Path) -> dict:
    """Read a JSON split manifest.

    Accepted forms: ``{"test": [...], "train": [...]}`` (one training list for every n) or
    ``{"test": [...], "train": {"3": [...], "6": [...]}}``; ``train_pool`` optional.
    """
    path = Path(path)
    problem = file_problem(path, "split manifest")
    if problem:
        raise ValueError(problem)
    try:
        data = json.loads(path.read_bytes())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"cannot read split manifest {path}: {exc}; give a JSON object with 'test' and "
                         "'train'") from exc
    if not isinstance(data, dict) or "test" not in data or "train" not in data:
        raise ValueError(f"split manifest {path} must be a JSON object with 'test' and 'train'")
    if not isinstance(data["test"], list) or not isinstance(data["train"], (list, dict)):
        raise ValueError(f"split manifest {path}: 'test' must be a list and 'train' a list or "
                         "an object mapping n to a list")
    return data


def make_split(names: list[str], ns: list[int] | tuple[int, ...] = (3, 6, 9, 12),
               manifest: dict | str | Path | None = None) -> Split:
    """The split of ``names`` for each n in ``ns`` (the protocol rule unless a manifest is given).

    With a manifest, its names must all be in ``names``, test and train must not overlap; a
    single train list is used for every n (its length is n, recorded under that key); a dict
    must contain every requested n.
    """
    names = sorted(names)
    if not names:
        raise ValueError("cannot split an empty image list")
    if manifest is None:
        test, pool = every8_split(names)
        return Split("every8", test, pool, {str(n): select_train(pool, n) for n in ns})
    data = load_manifest(manifest) if isinstance(manifest, (str, Path)) else manifest
    known = set(names)
    test = sorted(data["test"])
    train_spec = data["train"]
    if isinstance(train_spec, list):
        train = {str(len(train_spec)): list(train_spec)}
        pool = sorted(data.get("train_pool", train_spec))
    else:
        train = {str(k): list(v) for k, v in train_spec.items()}
        missing_n = [str(n) for n in ns if str(n) not in train]
        if missing_n:
            raise ValueError(f"split manifest has no training list for n = {missing_n}")
        if ns:
            train = {str(n): train[str(n)] for n in ns}
        pool = sorted(data.get("train_pool", sorted({x for v in train.values() for x in v})))
    every = set(test) | set(pool) | {x for v in train.values() for x in v}
    unknown = sorted(every - known)
    if unknown:
        raise ValueError(f"split manifest names images that are not in the scene: {unknown[:5]}")
    overlap = sorted(set(test) & {x for v in train.values() for x in v})
    if overlap:
        raise ValueError(f"split manifest puts images in both test and train: {overlap[:5]}")
    return Split("manifest", test, pool, train)


def write_split(path: str | Path, split: Split) -> Path:
    """Write ``split.json`` (docs/contracts.md) atomically."""
    return write_json(path, split.to_json())


def read_split(path: str | Path) -> Split:
    """Read a ``split.json`` written by :func:`write_split`, checked: every name a plain file
    name (``../x.png`` would lead a command out of its folders), no name twice in a list.

    Raises:
        ValueError: one line naming the file and what is wrong.
    """
    from runtime.names import check_name_list

    try:
        data = json.loads(Path(path).read_text())
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"{path}: not a split.json (JSON): {exc}") from None
    if not isinstance(data, dict):
        raise ValueError(f"{path}: split.json holds a JSON object, not {type(data).__name__}")
    for key in ("rule", "test", "train_pool", "train"):
        if key not in data:
            raise ValueError(f"{path}: split.json lacks the key {key!r}")
    if not isinstance(data["train"], dict):
        raise ValueError(f"{path}: 'train' must map n to a list of names")
    lists = {"test": data["test"], "train_pool": data["train_pool"],
             **{f"train {k}": v for k, v in data["train"].items()}}
    for what, names in lists.items():
        if not isinstance(names, list):
            raise ValueError(f"{path}: '{what}' must be a list of image names")
        check_name_list(names, path, f"{what} name")  # plain names, none twice
    return Split(data["rule"], data["test"], data["train_pool"], data["train"])
