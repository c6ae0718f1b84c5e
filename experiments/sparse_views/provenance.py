"""Was an evaluation registered before its runs? The registration's commit against the runs' times.

A pre-registered evaluation is one whose values, scenes, seeds and budget were committed before
any run on its scenes. This module reads that from the repository's git history, never from
prose:

- the registration's commit: for a seed comparison the commit that first added its
  ``registered/*.yaml`` (``git log --follow --diff-filter=A -- FILE``, through renames); for the
  sparse-view grid, per evaluation scene, the commit that last gave the scene its
  ``role: evaluation`` in ``scenes.yaml`` (each commit of the file against its parent's version);
- each run's time, from its record: ``started_at`` (UTC, written by the runner) is exact; an
  older record holds only ``recorded``, the day it was written (read as a UTC day, the clock of
  this project's machines), which places the run within that day and before the first commit of
  the record file (followed through renames; :meth:`History.first_commits`).

A run is *after* its registration when its earliest possible time is at or after the
registration's commit time, *before* when its latest possible time is at or before it, and
*unplaced* otherwise (a day-stamped record of the commit's own day). The block that
:func:`check` returns goes into the JSON records; :func:`sentence` states it in a page without
a commit hash or a date (the docs hold neither). Without usable history (no git, not a
checkout, a shallow clone) the block says ``registration not verifiable here`` and nothing fails.
"""

from __future__ import annotations

import shutil
import subprocess
from datetime import datetime, timedelta, timezone
from pathlib import Path

NOT_VERIFIABLE = "registration not verifiable here"
FILE_LOG = "git log --follow --diff-filter=A -- FILE"
ROLE_LOG = "git log --follow -p -- FILE"


def _git(root: Path, *args: str) -> str:
    proc = subprocess.run(["git", "-C", str(root), *args], capture_output=True, text=True, timeout=120)
    if proc.returncode != 0:
        raise RuntimeError(proc.stderr.strip().splitlines()[-1] if proc.stderr.strip() else f"git {args[0]} failed")
    return proc.stdout


def _time(text: str) -> datetime:
    return datetime.fromisoformat(text.strip()).astimezone(timezone.utc)


class History:
    """The git history of the repository holding ``path``, read lazily and once per query kind."""

    def __init__(self, root: Path):
        self.root = root
        self._first: dict[str, tuple[str, datetime]] | None = None

    @classmethod
    def of(cls, path: Path) -> History | str:
        """The history around ``path``, or the reason there is none to trust (a string)."""
        if shutil.which("git") is None:
            return "no git here"
        folder = Path(path).resolve()
        folder = next((p for p in (folder, *folder.parents) if p.is_dir()), folder)
        try:
            root = Path(_git(folder, "rev-parse", "--show-toplevel").strip())
            if _git(root, "rev-parse", "--is-shallow-repository").strip() == "true":
                return "a shallow clone: its oldest commits are missing"
            _git(root, "rev-parse", "--verify", "-q", "HEAD")
        except (RuntimeError, OSError, subprocess.TimeoutExpired):
            return "not a git checkout with history"
        return cls(root)

    def rel(self, path: Path) -> str:
        return Path(path).resolve().relative_to(self.root).as_posix()

    def first_added(self, path: Path) -> tuple[str, datetime] | None:
        """The commit that first added ``path`` (followed through renames) and its time."""
        out = _git(self.root, "log", "--follow", "--diff-filter=A", "--format=%H %cI", "--", self.rel(path))
        lines = out.split()
        return (lines[-2], _time(lines[-1])) if lines else None

    def first_commits(self) -> dict[str, tuple[str, datetime]]:
        """Every tracked path -> the commit that first added the file now there, followed
        through renames (a deleted path's entry ends with it: a file added again is a new one)."""
        if self._first is None:
            out = _git(self.root, "log", "--reverse", "--topo-order", "-M", "--name-status", "--diff-filter=ADR",
                       "--format=@%H %cI")
            first: dict[str, tuple[str, datetime]] = {}
            here = None
            for line in out.splitlines():
                if line.startswith("@"):
                    commit, when = line[1:].split()
                    here = (commit, _time(when))
                    continue
                parts = line.split("\t")
                if not line or here is None:
                    continue
                if parts[0] == "A":
                    first[parts[1]] = here
                elif parts[0] == "D":
                    first.pop(parts[1], None)
                elif parts[0].startswith("R") and len(parts) == 3:
                    first[parts[2]] = first.pop(parts[1], here)
            self._first = first
        return self._first

    def role_since(self, scenes_yaml: Path, role: str) -> dict[str, tuple[str, datetime]]:
        """Scene name -> the commit that last gave it ``role`` in ``scenes_yaml`` (its version
        there against its parent's: the latest commit where the scene took the role) and its
        time; only scenes whose committed role is ``role`` at HEAD."""
        import yaml

        loader = getattr(yaml, "CSafeLoader", yaml.SafeLoader)
        out = _git(self.root, "log", "--follow", "--name-only", "--format=@%H %cI", "--", self.rel(scenes_yaml))
        commits: list[tuple[str, datetime, str]] = []  # newest first: commit, time, path there
        for line in out.splitlines():
            if line.startswith("@"):
                c, t = line[1:].split()
                commits.append((c, _time(t), ""))
            elif line.strip() and commits and not commits[-1][2]:
                commits[-1] = (*commits[-1][:2], line.strip())

        def roles(rev: str, path: str) -> dict[str, str] | None:
            try:
                text = _git(self.root, "show", f"{rev}:{path}")
            except RuntimeError:
                return None
            try:
                data = yaml.load(text, Loader=loader)
            except yaml.YAMLError:  # a version that did not parse registered nothing
                return None
            scenes = data.get("scenes") if isinstance(data, dict) else None
            return {str(s.get("name")): s.get("role") for s in scenes or [] if isinstance(s, dict)}

        if not commits:
            return {}
        now = roles("HEAD", commits[0][2]) or {}
        want = {s for s, r in now.items() if r == role}
        found: dict[str, tuple[str, datetime]] = {}
        for i, (c, t, path) in enumerate(commits):
            if not want - set(found):
                break
            mine = roles(c, path) or {}
            older = commits[i + 1][2] if i + 1 < len(commits) else path
            parent = roles(f"{c}^", path) or roles(f"{c}^", older) or {}
            for s in want - set(found):
                if mine.get(s) == role and parent.get(s) != role:
                    found[s] = (c, t)
        return found


def run_window(rec: dict, committed: datetime | None) -> tuple[datetime | None, datetime | None, str]:
    """When the run of record ``rec`` can have happened: (earliest, latest, source). ``committed``:
    the first commit time of its record file (None: not committed). A stamp that does not read
    as a time counts as absent."""
    try:
        t = _time(str(rec["started_at"]))
        return t, t, "started_at"
    except (KeyError, ValueError):
        pass
    try:
        day = datetime.strptime(str(rec["recorded"])[:10], "%Y-%m-%d").replace(tzinfo=timezone.utc)
        end = day + timedelta(days=1)
        return day, min(end, committed) if committed else end, "recorded day"
    except (KeyError, ValueError):
        return None, committed, "record's first commit"


def place(rec: dict, committed: datetime | None, registered: datetime) -> str:
    """``after``, ``before`` or ``unplaced``: the run of ``rec`` against the registration time."""
    earliest, latest, _ = run_window(rec, committed)
    if latest is not None and latest <= registered:
        return "before"
    if earliest is not None and earliest >= registered:
        return "after"
    return "unplaced"


def _block(file: str, commit: str | None, when: datetime | None, runs: dict[str, str]) -> dict:
    """The registration block of the records: ``runs`` maps a run's name to its placing."""
    before = sorted(k for k, v in runs.items() if v == "before")
    unplaced = sorted(k for k, v in runs.items() if v == "unplaced")
    return {"file": file, "commit": commit, "committed_at": when.isoformat() if when else None,
            "runs": len(runs), "runs_after": sum(v == "after" for v in runs.values()),
            "runs_before": before, "runs_unplaced": unplaced,
            "pre_registered": False if (before or commit is None) else (None if unplaced else True)}


def _not_verifiable(file: str, reason: str, runs: int) -> dict:
    return {"file": file, "verifiable": False, "reason": f"{NOT_VERIFIABLE}: {reason}", "runs": runs,
            "pre_registered": None}


def _runs(history: History, records: list[Path], registered: datetime | None) -> dict[str, str]:
    import json

    first = history.first_commits()
    out = {}
    for p in records:
        key = history.rel(p) if Path(p).resolve().is_relative_to(history.root) else None
        committed = first.get(key)[1] if key in first else None
        out[Path(p).stem] = "before" if registered is None else place(json.loads(Path(p).read_text()), committed,
                                                                     registered)
    return out


def check(registration: Path, records: list[Path], shown: str) -> dict:
    """A seed comparison's registration (``registered/*.yaml``) against its run records.
    ``shown``: the file's name in the records (relative to the repository)."""
    history = History.of(registration)
    if isinstance(history, str):
        return _not_verifiable(shown, history, len(records))
    try:
        added = history.first_added(registration)
        runs = _runs(history, records, added[1] if added else None)
    except (RuntimeError, ValueError, OSError, subprocess.TimeoutExpired) as exc:
        return _not_verifiable(shown, str(exc), len(records))
    return _block(shown, *(added or (None, None)), runs)


def check_scenes(scenes_yaml: Path, records: dict[str, list[Path]], shown: str, role: str = "evaluation") -> dict:
    """The sparse-view grid: per scene of ``records`` (scene -> its run records) the commit that
    gave it ``role`` against its runs; totals over the scenes, ``commit`` and ``committed_at``
    those of the latest scene registration."""
    history = History.of(scenes_yaml)
    total = sum(map(len, records.values()))
    if isinstance(history, str):
        return _not_verifiable(shown, history, total)
    try:
        since = history.role_since(scenes_yaml, role)
        per = {s: _block(shown, *since.get(s, (None, None)), _runs(history, rs, since.get(s, (None, None))[1]))
               for s, rs in sorted(records.items())}
    except (RuntimeError, ValueError, OSError, subprocess.TimeoutExpired) as exc:
        return _not_verifiable(shown, str(exc), total)
    dated = [b for b in per.values() if b["commit"]]
    last = max(dated, key=lambda b: b["committed_at"]) if dated else None
    out = {"file": shown, "role": role, "commit": last["commit"] if last else None,
           "committed_at": last["committed_at"] if last else None, "runs": total,
           "runs_after": sum(b["runs_after"] for b in per.values()),
           "runs_before": sorted(r for b in per.values() for r in b["runs_before"]),
           "runs_unplaced": sorted(r for b in per.values() for r in b["runs_unplaced"]),
           "unregistered_scenes": sorted(s for s, b in per.items() if b["commit"] is None)}
    out["pre_registered"] = (False if out["runs_before"] or out["unregistered_scenes"]
                             else None if out["runs_unplaced"] else True)
    out["scenes"] = {s: {k: b[k] for k in ("commit", "committed_at", "runs", "runs_after", "runs_before",
                                           "runs_unplaced")} for s, b in per.items()}
    return out


def _names(runs: list[str], most: int = 20) -> str:
    shown = ", ".join(f"`{r}`" for r in runs[:most])
    return shown + (f" and {len(runs) - most} more" if len(runs) > most else "")


def sentence(block: dict, what: str) -> str:
    """One Markdown sentence of ``block`` (:func:`check` or :func:`check_scenes`) with no commit
    hash or date; ``what`` names the registering commit by its change, e.g. "commit that added `FILE`"."""
    cmd = f"`{ROLE_LOG if 'role' in block else FILE_LOG}`"
    if block.get("verifiable") is False:
        return f"{block['reason'][0].upper()}{block['reason'][1:]} (it reads `{cmd[1:-1]}`)."
    n = block["runs"]
    if block["commit"] is None or block.get("unregistered_scenes"):
        who = (f"the scenes {', '.join(block['unregistered_scenes'])} have no committed registration"
               if block.get("unregistered_scenes") else f"`{block['file']}` is not committed")
        return f"Not pre-registered: {who}, so none of their runs can follow it."
    if block["runs_before"]:
        more = (f"; {len(block['runs_unplaced'])} more cannot be placed before or after their registration"
                if block["runs_unplaced"] else "")
        b = len(block["runs_before"])
        return (f"Not pre-registered: {b} of the {n} runs {'was' if b == 1 else 'were'} made before the "
                f"{what} ({cmd}): {_names(block['runs_before'])}{more}.")
    if block["runs_unplaced"]:
        return (f"Registered in the {what} ({cmd}); {block['runs_after']} of the {n} runs are later "
                f"and {len(block['runs_unplaced'])} cannot be placed before or after their registration: their records "
                f"hold only the day they were written, the registration's own day.")
    if n == 0:
        return f"Registered in the {what} ({cmd}); no run is recorded yet."
    return f"Registered in the {what}, before all {n} of {'their' if 'role' in block else 'its'} runs ({cmd})."
