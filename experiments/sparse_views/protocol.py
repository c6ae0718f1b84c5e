"""The protocol file as the benchmark runs it: scenes, their role, where their data is.

``scenes.yaml`` is read and checked once, by :func:`experiments.sparse_views.fetch_scenes.load_scenes`;
this module resolves each scene's data folder: ``--data DIR`` (or ``$SPARSE_VIEWS_DATA``) means
``DIR/<name>``, as ``fetch_scenes.py DIR`` leaves them; otherwise the scene's ``local`` entry
(relative to the repository), which is where this project's own machines keep it.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

from experiments.sparse_views.fetch_scenes import ROLES, RUN_ROLES, SCENES_YAML, load_scenes

HERE = Path(__file__).resolve().parent
REPO = HERE.parents[1]
PROTOCOL = SCENES_YAML
DATA_ENV = "SPARSE_VIEWS_DATA"
__all__ = ["Scene", "load", "PROTOCOL", "ROLES", "RUN_ROLES", "DATA_ENV", "REPO"]


@dataclass(frozen=True)
class Scene:
    """One protocol scene. ``path`` is None for a generated scene (``generate`` set: a command
    whose ``{out}`` is the scene folder to write). ``background``: the RGB every recipe trains
    and renders against on this scene (``scenes.yaml``'s ``background``); None: the trainer's."""

    name: str
    role: str
    kind: str
    views: tuple[int, ...]
    path: Path | None = None
    convert: tuple[str, ...] = ()
    generate: tuple[str, ...] = ()
    source: dict = field(default_factory=dict, compare=False)
    background: tuple[float, float, float] | None = None

    @property
    def available(self) -> bool:
        return self.path is None or self.path.is_dir()


def load(protocol: Path = PROTOCOL, data: Path | None = None) -> list[Scene]:
    """The scenes of ``protocol`` with their data folders resolved (see the module docstring);
    :class:`~experiments.sparse_views.fetch_scenes.ScenesError` (a ValueError) for a bad file."""
    data = data or (Path(os.environ[DATA_ENV]) if os.environ.get(DATA_ENV) else None)
    out = []
    for s in load_scenes(protocol):
        src = dict(s.get("source") or {}, licence=s.get("licence"), cameras=s.get("cameras"))
        views = tuple(s["views"])
        bg = tuple(float(v) for v in s["background"]) if "background" in s else None
        if s.get("generate"):
            out.append(Scene(s["name"], s["role"], str(s.get("kind", "")), views, None, (),
                             tuple(map(str, s["generate"])), src, bg))
            continue
        if data is not None:
            path = Path(data) / s["name"]
        elif s.get("local"):
            path = Path(s["local"]) if Path(s["local"]).is_absolute() else REPO / s["local"]
        else:
            raise ValueError(f"{protocol}: scene {s['name']} has neither 'local' nor 'generate'")
        out.append(Scene(s["name"], s["role"], str(s.get("kind", "")), views, path,
                         tuple(map(str, s.get("convert", []))), (), src, bg))
    return out
