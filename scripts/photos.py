"""Your own photos in one command: cameras, a trained model and a view of it.

    python scripts/photos.py PHOTOS [--out DIR] [--init vggt|colmap|both] [--dense] [--iterations N]
                             [--max-size PX] [--cores N] [--device auto|cpu|cuda|cuda:N] [-v] [-n] [--unlock]
                             [-- SNAKEMAKE ARGS ...]

PHOTOS is a folder of photographs of one scene (3 or more; no camera files needed), as a phone
or camera takes them: portrait and landscape mixed, EXIF-rotated (turned upright when they are
prepared; the run names them), of several sizes (each size gets its own camera). Every photo
that cannot be used (a format the readers do not take, such as HEIC; a file that does not
decode; one too small) is named, all in one line, before anything runs. Every photo trains:
there are no reference cameras and no held-out views, so there are no image metrics, only the
model and a render of every photo. Every stage works at a working resolution: the long side at
most camio.prepare.PHOTO_MAX_SIZE pixels unless ``--max-size`` says otherwise (0 = the photos'
own size); the run says which.

The run prints snakemake's progress lines, each naming the step that finished, the workflow's
own messages, and every HEARTBEAT_S seconds (workflow/scripts/progress.py) the time elapsed and
the newest log line; ``-v`` shows snakemake's job blocks too. SIGINT (Ctrl-C) or SIGTERM stops
the run: it is passed on as SIGINT to snakemake and the jobs it runs (each job ends within a second,
tidying its output folder; snakemake starts no other); the script waits for them, says so in one
line and exits 128 + the signal's number; the same command again resumes (snakemake
--rerun-incomplete redoes the jobs that were cut short). A run killed outright (SIGKILL, a power loss) leaves snakemake's lock behind: the next
run says so in one line, and ``--unlock`` removes that lock when no run of the folder is alive on
this machine. This writes DIR/config.yaml (the workflow's
configuration for this folder) and DIR/split.json (every photo trains), then runs the project's
Snakemake workflow on it, so a second run resumes and the same config runs on a cluster.
A rerun writes into DIR/config.yaml only the folder's keys and those its flags set, keeping
every other edit made there (a flag not given leaves its key as the file has it); it refuses a
config.yaml that it did not write, or wrote for another folder.

    snakemake --profile workflow/profiles/slurm --configfile DIR/config.yaml

What the run leaves (DIR/photos.md lists the paths and the exact `view` command):

    DIR/photos/<name>/n<N>/<init>/sparse/0                 the initialiser's cameras (COLMAP model)
    DIR/photos/<name>/n<N>/<init>/<mode>/bridge/seed.ply   the seed point cloud
    DIR/photos/<name>/n<N>/<init>/<mode>/train/model.ply   the trained model
    DIR/photos/<name>/n<N>/<init>/<mode>/train_renders/    a render of every photo
    DIR/photos.md, DIR/report/index.html                   what ran, and why not where it did not

Without the VGGT-1B checkpoint (and no way to download it) VGGT is skipped with one line
saying why, and COLMAP runs alone. ``--dense`` adds, for each initialiser, multi-view stereo of
the photos on its cameras (``colmap_mvs``, ``vggt_mvs``: evaluation/initialisers/mvs): a dense
seed with a confidence per point, which the Bridge turns into opacity (Eq. 2).
"""

from __future__ import annotations

import argparse
import contextlib
import os
import shlex
import signal
import subprocess
import sys
import threading
from pathlib import Path
from typing import Iterable, Iterator

from runtime.stops import stops_early

stops_early()  # a stop while the script loads (until snakemake runs): one line, exit 128 + the signal

import yaml  # noqa: E402

from evaluation.initialisers import registry

REPO = Path(__file__).resolve().parents[1]
#: --init: the method and its baseline (the registry's roles, Table I's pair), alone or both
_PAIR = [registry.with_role(role) for role in registry.ROLES]
INITS = {**{name: [name] for name in _PAIR}, "both": _PAIR}
DATASET = "photos"
#: seconds between two SIGINTs to snakemake after a stop, until it says it is stopping
SIGINT_AGAIN_S = 0.5
HEADER = "# Written by scripts/photos.py for"
#: the keys a new config.yaml starts with, which a rerun leaves to the file unless a flag sets them
#: how often (iterations) a photo run's trainer replaces train/snapshot.ply, which the viewer
#: follows live (train.snapshot_every; written on the first run, yours to change after)
SNAPSHOT_EVERY = 100
FIRST_WRITE = {"initialisers": INITS["both"], "evaluation": {"testpose": False},
               "train": {"snapshot_every": SNAPSHOT_EVERY}}


def _fail(msg: str) -> int:
    print(f"scripts/photos.py: error: {msg}", file=sys.stderr)
    return 2


def photo_names(folder: Path) -> list[str]:
    """The photographs of ``folder``, as `camio convert --format folder` reads them."""
    from camio.scene import load_scene

    return list(load_scene(folder, format="folder").names)


def photo_sizes(folder: Path, names: list[str], max_size: int | None) -> tuple[list[tuple[int, int]], set]:
    """(each photo's (width, height) as displayed, the set of working sizes ``max_size`` gives
    them: :func:`camio.prepare.photo_max_size`, as camio convert sizes them)."""
    from camio.images import image_size, working_size
    from camio.prepare import photo_max_size

    sizes = [image_size(folder / n) for n in names]
    cap = photo_max_size(max_size, False)
    return sizes, {working_size(w, h, cap) for w, h in sizes}


def one_grid_problem(initialisers: list[str], working: set) -> str | None:
    """Why the initialisers cannot run on photos of several working sizes (None: they can).
    Multi-view stereo (the ``*_mvs`` initialisers) writes one grid for all views."""
    mvs = [i for i in initialisers if str(i).endswith("_mvs")]
    if not mvs or len(working) < 2:
        return None
    shown = ", ".join(f"{w}x{h}" for w, h in sorted(working))
    return (f"multi-view stereo ({', '.join(mvs)}: --dense) needs photos of one size, and these have "
            f"{len(working)} ({shown}); run without --dense (and drop {', '.join(mvs)} from config.yaml's "
            "initialisers), or keep only the photos of one orientation")


def make_config(folder: Path, out: Path, names: list[str], inits: list[str] | None = None,
                iterations: int | None = None, vggt: dict | None = None, max_size: int | None = None,
                device: str | None = None) -> dict:
    """The keys of the workflow configuration of one photo folder (results under ``out``) that
    this script sets: the folder's scene, and the keys of the flags given (None: not given)."""
    scene = scene_name(folder)
    block: dict = {
        "path": str(folder.resolve()),
        "format": "folder",
        "reference": False,
        "split": {"rule": "manifest", "manifest": str(out / "split.json")},
        "views": [len(names)],
    }
    if max_size is not None:
        block["max_size"] = max_size
    cfg: dict = {"results": str(out), "datasets": {DATASET: {"scenes": {scene: block}}}, "views": [len(names)]}
    if inits is not None:
        cfg["initialisers"] = inits
    if iterations is not None:
        cfg["train"] = {"iterations": iterations, "eval_every": max(1, iterations)}
    if vggt or device:
        cfg["vggt"] = {**(vggt or {}), **({"device": device} if device else {})}
    if device:
        cfg.setdefault("train", {})["device"] = device
    return cfg


def live_view_lines(cfg: dict, out: Path, scene: str, n: int) -> list[str]:
    """The command that watches each run train (its train/snapshot.ply, replaced every
    ``train.snapshot_every`` iterations); [] when the config writes no snapshots."""
    every = (cfg.get("train") or {}).get("snapshot_every")
    if not every:
        return []
    from evaluation.initialisers.registry import get

    schema = yaml.safe_load((REPO / "workflow" / "schemas" / "config.schema.yaml").read_text())
    modes = (cfg.get("bridge") or {}).get("modes") or schema["properties"]["bridge"]["properties"]["modes"]["default"]
    lines = [f"watch a run train (the model every {every} iterations, in the browser):"]
    for init in cfg["initialisers"]:
        for mode in (modes if get(init).confidence else ["uniform"]):
            run = out / DATASET / scene / f"n{n}" / init / mode / "train"
            lines.append(f"  python -m splat_train view --model {shlex.quote(str(run))}")
    return lines


def scene_name(folder: Path) -> str:
    scene = folder.resolve().name
    return "".join(c if c.isalnum() or c in "_.-" else "_" for c in scene).lstrip("_.-") or "scene"


def merge_config(old: dict, new: dict) -> dict:
    """``old`` with ``new``'s keys written over it: mappings merged key by key, anything else
    replaced; the keys ``new`` lacks stay as ``old`` has them."""
    merged = dict(old)
    for key, value in new.items():
        if isinstance(value, dict) and isinstance(merged.get(key), dict):
            merged[key] = merge_config(merged[key], value)
        else:
            merged[key] = value
    return merged


def header(folder: Path) -> str:
    """The first line of the config.yaml this script writes: how it knows its own file."""
    return f"{HEADER} {folder.resolve()}"


def read_own_config(path: Path, folder: Path) -> dict | None:
    """The config.yaml this script wrote for ``folder`` at ``path`` (None: there is none).

    Raises:
        ValueError: a file it did not write, wrote for another folder, or cannot read.
    """
    if not path.is_file():
        return None
    text = path.read_text()
    first = text.split("\n", 1)[0].strip()
    if not first.startswith(HEADER):
        raise ValueError(f"{path} was not written by scripts/photos.py (its first line is not '{HEADER} ...'); "
                         "choose another --out, or move that file away")
    if first != header(folder):
        raise ValueError(f"{path} was written for another folder ({first[len(HEADER):].strip()}); "
                         "choose another --out, or remove that file to start over")
    try:
        cfg = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ValueError(f"cannot read {path}: {' '.join(str(exc).split())}; fix it, or remove it to start over")
    if not isinstance(cfg, dict):
        raise ValueError(f"{path} holds no mapping of keys; fix it, or remove it to start over")
    return cfg


def _write_if_changed(path: Path, text: str) -> None:
    """Rewrite only when the content changes, so that a rerun resumes rather than restarts."""
    if path.is_file() and path.read_text() == text:
        return
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


def working_resolution(sizes: list[tuple[int, int]], max_size: int | None) -> str:
    """The line that states the working resolution (camio convert's, which the workflow runs)."""
    from camio.prepare import describe_working_size, photo_max_size

    return describe_working_size(sizes, photo_max_size(max_size, False))


def visible_gpu(device: str) -> tuple[str, dict]:
    """(the device the workflow's jobs are given, the environment that goes with it): cuda:N
    becomes cuda with only GPU N visible (CUDA_VISIBLE_DEVICES, counted among those already
    visible); any other name is passed on as it is."""
    if not device.startswith("cuda:"):
        return device, {}
    index = int(device.split(":", 1)[1])
    seen = os.environ.get("CUDA_VISIBLE_DEVICES")
    ids = [x.strip() for x in seen.split(",") if x.strip()] if seen else None
    if ids is not None and not ids:
        raise ValueError(f"--device {device}: CUDA_VISIBLE_DEVICES={seen!r} shows no GPU; use --device cpu")
    if ids is not None and index >= len(ids):
        raise ValueError(f"--device {device}: CUDA_VISIBLE_DEVICES={seen} shows {len(ids)} GPU(s); "
                         f"choose cuda:0..cuda:{len(ids) - 1}")
    return "cuda", {"CUDA_VISIBLE_DEVICES": ids[index] if ids is not None else str(index)}


def snakemake_locks(out: Path) -> list[Path]:
    """Snakemake's lock files (REPO/.snakemake/locks/N.input.lock, N.output.lock: one path a
    line) that name a file inside ``out``: a run of this folder holds them, or a run that was
    killed (SIGKILL, a power loss) left them behind, and snakemake then refuses every later run."""
    found = []
    for lock in sorted((REPO / ".snakemake" / "locks").glob("*.lock")):
        try:
            lines = lock.read_text(errors="replace").splitlines()
        except OSError:
            continue
        for line in lines:
            path = Path(os.path.abspath(REPO / line.strip())) if line.strip() else None
            if path is not None and (path == out or out in path.parents):
                found.append(lock)
                break
    return found


def snakemake_runs(out: Path) -> list[int]:
    """The processes on this machine (pids) that run snakemake with ``out`` in their command line."""
    pids = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit() or int(entry.name) == os.getpid():
            continue
        try:
            argv = (entry / "cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        if any(b"snakemake" in a for a in argv) and any(os.fsencode(out) in a for a in argv):
            pids.append(int(entry.name))
    return pids


def check_locks(out: Path, unlock: bool) -> str | None:
    """None when snakemake may run on ``out`` (after removing, with ``unlock``, the locks of a run
    that is no longer alive), else the one line that says why not and what to do."""
    locks = snakemake_locks(out)
    if not locks:
        return None
    pids = snakemake_runs(out)
    if pids:
        return (f"--out {out} is being run by snakemake (pid {pids[0]}, lock {locks[0]}): wait for it to finish "
                "or stop it (Ctrl-C, or kill -INT the pid)")
    if not unlock:
        return (f"--out {out} is locked ({locks[0]}) by a snakemake run that is no longer running on this machine "
                "(killed?); if no run of this folder goes on elsewhere (a cluster job), run the same command with "
                "--unlock")
    for lock in locks:
        lock.unlink(missing_ok=True)
    print(f"[photos] --unlock: removed {len(locks)} lock file(s) that a snakemake run of {out}, no longer running, "
          "left behind", flush=True)
    return None


def run_snakemake(cmd: list[str], out: Path, env: dict, verbose: bool, heartbeat: bool) -> tuple[int, int | None]:
    """Run snakemake ``cmd``, its output passed through workflow/scripts/progress.py's filters
    (all of it with ``verbose``) with a heartbeat; a SIGINT or SIGTERM stops it (passed on as SIGINT).

    Returns:
        (snakemake's exit code, the signal that stopped the run or None).
    """
    from progress import Heartbeat, acts_on_stop, annotate, brief

    lock = threading.Lock()

    def write(line: str) -> None:
        with lock:
            sys.stdout.write(line)
            sys.stdout.flush()

    # a session of its own: a Ctrl-C at the terminal reaches snakemake once, through forward();
    # its SIGINT at the default even where this command was started with it ignored (a background
    # job): forward() stops snakemake with SIGINT whatever signal stopped this command
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, bufsize=1,
                            start_new_session=True, env={**os.environ, **env},
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    stopped: list[int] = []
    acted = threading.Event()

    def interrupt(whole_group: bool) -> None:
        with contextlib.suppress(ProcessLookupError, PermissionError):
            if whole_group:  # the session's group: snakemake and the jobs it runs (shell children)
                os.killpg(proc.pid, signal.SIGINT)
            else:
                proc.send_signal(signal.SIGINT)

    def insist() -> None:
        # snakemake (9.27) loses a SIGINT that lands while it writes a log line (its log handler
        # passes over a KeyboardInterrupt), and it writes many between two jobs. Until it says it
        # is stopping (or exits), snakemake alone gets the SIGINT again; its jobs had theirs
        while not acted.wait(SIGINT_AGAIN_S) and proc.poll() is None:
            interrupt(whole_group=False)

    def forward(sig, _frame) -> None:
        # SIGINT is snakemake's "stop now": it starts no other job, marks the running ones'
        # outputs incomplete and exits once they end, which the same SIGINT makes them do (each
        # stage command ends within a second on it, tidying its output folder). On a SIGTERM
        # snakemake waits for its jobs to end by themselves and (snakemake 9.27) hangs when the
        # signal falls between two jobs
        if not stopped:
            threading.Thread(target=insist, name="sigint-again", daemon=True).start()
        stopped.append(sig)
        interrupt(whole_group=True)

    def watched(stream: Iterable[str]) -> Iterator[str]:
        for line in stream:
            if stopped and acts_on_stop(line):
                acted.set()
            yield line

    saved = {sig: signal.signal(sig, forward) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        lines = annotate(watched(proc.stdout), "[photos]")
        # once stopped, snakemake's own account of the stop (its jobs cut short) only with -v
        lines = lines if verbose else (ln for ln in brief(lines) if not stopped)
        if heartbeat:
            with Heartbeat(out, write, "[photos]"):
                for line in lines:
                    write(line)
        else:
            for line in lines:
                write(line)
        rc = proc.wait()
    finally:
        for sig, handler in saved.items():
            signal.signal(sig, handler)
    return rc, (stopped[0] if stopped else None)


def main(argv: list[str] | None = None) -> int:
    from camio.photo_folder import describe_problems, photo_problems
    from camio.prepare import PHOTO_MAX_SIZE
    from runtime.cliargs import device_name
    from vggt_init.defaults import IMAGE_SIZE

    argv = list(sys.argv[1:] if argv is None else argv)
    extra: list[str] = []
    if "--" in argv:
        i = argv.index("--")
        argv, extra = argv[:i], argv[i + 1:]
    p = argparse.ArgumentParser(prog="scripts/photos.py", description=__doc__.split("\n\n")[0],
                                epilog="Arguments after -- go to snakemake (e.g. -- --profile "
                                       "workflow/profiles/slurm).")
    p.add_argument("photos", type=Path, help="folder of the photographs (3 or more)")
    p.add_argument("--out", type=Path, help="results folder (default: results_photos/<folder name>)")
    p.add_argument("--init", choices=sorted(INITS),
                   help="initialiser: vggt, colmap, or both (default: config.yaml's, else both; VGGT is "
                        "skipped, with the reason, where its checkpoint is missing)")
    p.add_argument("--dense", action="store_true",
                   help="also seed from multi-view stereo of the photos on each initialiser's cameras "
                        "(colmap_mvs, vggt_mvs; without it, config.yaml's initialisers stay unless --init "
                        "is given)")
    p.add_argument("--iterations", type=int, help="training steps (default: the workflow's, "
                                                  "workflow/schemas/config.schema.yaml)")
    p.add_argument("--vggt-checkpoint", dest="vggt_checkpoint",
                   help="VGGT weights file (default: the search order of vggt_init/checkpoint.py)")
    p.add_argument("--vggt-model-config", dest="vggt_model_config",
                   help="VGGT model configuration JSON (default: VGGT-1B)")
    p.add_argument("--vggt-image-size", dest="vggt_image_size", type=int,
                   help=f"VGGT input width (multiple of 14; default: config.yaml's, else {IMAGE_SIZE})")
    p.add_argument("--max-size", dest="max_size", type=int, metavar="PX",
                   help=f"long side of the working images every stage reads, pixels (default: "
                        f"config.yaml's, else {PHOTO_MAX_SIZE}; 0 = the photos' own size)")
    p.add_argument("--cores", type=int, default=2, help="cores snakemake may use (default %(default)s; at least 1)")
    p.add_argument("--device", type=device_name,
                   help="where VGGT and training run: auto (CUDA when a job sees a GPU, else CPU), cpu, cuda, or "
                        "cuda:N, the GPU of index N (the jobs see only that one: CUDA_VISIBLE_DEVICES; give it "
                        "again on a rerun) (default: config.yaml's, else auto)")
    p.add_argument("-v", "--verbose", action="count", default=0, help="show snakemake's job blocks too")
    p.add_argument("-n", "--dry-run", action="store_true", dest="dry_run",
                   help="write the config and show the jobs, run nothing")
    p.add_argument("--unlock", action="store_true",
                   help="remove the locks a killed snakemake run of --out left behind (refused while such a run "
                        "is alive on this machine; make sure none runs elsewhere)")
    args = p.parse_args(argv)

    if not args.photos.is_dir():
        return _fail(f"{args.photos} is not a folder of photos")
    if args.iterations is not None and args.iterations < 1:
        return _fail(f"--iterations must be at least 1, got {args.iterations}")
    from camio.limits import MAX_IMAGE_SIDE  # the config schema's maximum of max_size too

    if args.max_size is not None and not 0 <= args.max_size <= MAX_IMAGE_SIDE:
        return _fail(f"--max-size must be 0 (the photos' own size) or a number of pixels up to {MAX_IMAGE_SIDE}, "
                     f"got {args.max_size}")
    if args.cores < 1:
        return _fail(f"--cores must be at least 1 (the cores snakemake may use), got {args.cores}")
    try:
        device, device_env = visible_gpu(args.device) if args.device else (None, {})
    except ValueError as exc:
        return _fail(str(exc))
    try:
        problems = photo_problems(args.photos)
    except OSError as exc:
        return _fail(f"cannot read the folder {args.photos}: {exc}")
    if problems:
        return _fail(describe_problems(args.photos, problems))
    try:
        names = photo_names(args.photos)
    except (ValueError, OSError) as exc:
        return _fail(str(exc).splitlines()[0])
    if len(names) < 3:
        return _fail(f"{args.photos} holds {len(names)} photo(s); at least 3 are needed")
    out = (args.out.expanduser() if args.out else Path("results_photos") / args.photos.resolve().name).absolute()
    if out.resolve() == args.photos.resolve() or args.photos.resolve() in out.resolve().parents:
        return _fail(f"--out {out} is inside the photo folder; choose a folder outside it")
    why = check_locks(out, args.unlock)  # before anything is written: snakemake's own refusal is a raw LockException
    if why:
        return _fail(why)
    vggt = {k: v for k, v in (("checkpoint", args.vggt_checkpoint), ("model_config", args.vggt_model_config),
                              ("image_size", args.vggt_image_size)) if v is not None}
    for key in ("checkpoint", "model_config"):
        if key in vggt:
            vggt[key] = str(Path(vggt[key]).absolute())
    try:
        old = read_own_config(out / "config.yaml", args.photos)
    except (ValueError, OSError) as exc:
        return _fail(str(exc))
    inits = None
    if args.init is not None or args.dense:
        kept = [i for i in (old or FIRST_WRITE).get("initialisers") or [] if not str(i).endswith("_mvs")]
        base = INITS[args.init] if args.init is not None else (kept or INITS["both"])
        inits = base + ([f"{i}_mvs" for i in base] if args.dense else [])
    cfg = make_config(args.photos, out, names, inits, args.iterations, vggt, args.max_size, device)
    cfg = merge_config(old if old is not None else FIRST_WRITE, cfg)

    sys.path.insert(0, str(REPO / "workflow" / "scripts"))
    from check_config import config_problems

    problems = config_problems(cfg)
    if problems:
        return _fail("; ".join(problems))
    block = cfg["datasets"][DATASET]["scenes"][scene_name(args.photos)]
    try:
        sizes, working = photo_sizes(args.photos, names, block.get("max_size"))
    except (ValueError, OSError) as exc:
        return _fail(str(exc).splitlines()[0])
    why = one_grid_problem(cfg["initialisers"], working)
    if why:
        return _fail(why)
    out.mkdir(parents=True, exist_ok=True)
    import json

    _write_if_changed(out / "split.json", json.dumps({"test": [], "train": {str(len(names)): names}}, indent=1) + "\n")
    if cfg != old:  # a file the rerun does not change stays as it is, comments and all
        _write_if_changed(out / "config.yaml", header(args.photos) + "\n" + yaml.safe_dump(cfg, sort_keys=False))
    print(f"[photos] {len(names)} photos in {args.photos}; config {out / 'config.yaml'}; "
          f"initialiser(s): {', '.join(cfg['initialisers'])}", flush=True)
    print(f"[photos] {working_resolution(sizes, block.get('max_size'))}", flush=True)
    from camio.images import describe_orientation

    turned = describe_orientation(args.photos, names)
    if turned:
        print(f"[photos] {turned}", flush=True)
    if device_env:
        print(f"[photos] device {args.device}: the jobs see only that GPU (CUDA_VISIBLE_DEVICES="
              f"{device_env['CUDA_VISIBLE_DEVICES']}) and use it as cuda", flush=True)
    for line in live_view_lines(cfg, out, scene_name(args.photos), len(names)):
        print(f"[photos] {line}", flush=True)
    cmd = [sys.executable, "-m", "snakemake", "--snakefile", str(REPO / "Snakefile"), "--directory", str(REPO),
           "--cores", str(args.cores), "--configfile", str(out / "config.yaml"), "--rerun-incomplete",
           *(["-n"] if args.dry_run else []), *extra]
    # the dry run's job list is what -n asks for: shown whole
    rc, stopped = run_snakemake(cmd, out, device_env, args.verbose or args.dry_run, not args.dry_run)
    if stopped is not None:
        print(f"[photos] stopped by {signal.Signals(stopped).name}: snakemake ended its jobs (exit {rc}); "
              "the same command resumes the run", file=sys.stderr, flush=True)
        return 128 + int(stopped)
    if rc != 0:
        print(f"[photos] FAILED (snakemake exit {rc}): see the output above and the logs under {out}",
              file=sys.stderr)
        return 1
    if not args.dry_run:
        print(f"[photos] done: {out / 'photos.md'} lists the cameras, seed, model, renders and the "
              "command to view the model", flush=True)
        summary = out / "photos.md"
        if summary.is_file():
            print(summary.read_text(), end="")
    return 0


if __name__ == "__main__":
    sys.exit(main())
