"""``python -m splat_train view``: serve one trained model (and its cameras) to a browser, or
follow a training run's snapshot live (:mod:`.source`)."""

from __future__ import annotations

import argparse
import errno
import logging
import sys
import threading
import webbrowser

from runtime.cliargs import deprecated_flags
from splat_train.view.server import DEFAULT_HOST, DEFAULT_PORT, IDLE_TIMEOUT_S, MAX_CONNECTIONS

log = logging.getLogger("splat_train.view")


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m splat_train view",
        description="Show a trained model (3DGS PLY, or the .splat or .spz `python -m splat_train export` writes) "
                    "in the browser (Spark on three.js, installed by `make install`), "
                    "with its cameras as frusta; pick a camera to look through it. Serves only these files, "
                    "read-only, on a local port. Given a training run's folder, follows its snapshot live.")
    p.add_argument("--model", required=True,
                   help="the trained model.ply (3DGS layout), or its export as .splat or .spz (the type is the "
                        "file's suffix; .spz needs the gsply package), or a training run's --out folder: then its "
                        "snapshot.ply (train with --snapshot-every N), reloaded in the page whenever the trainer "
                        "replaces it, or its model.ply while there is none. A changed file is checked again "
                        "and served only if it is still a model of its type")
    p.add_argument("--cameras", help="COLMAP model folder of the training cameras (drawn green)")
    p.add_argument("--test-cameras", dest="test_cameras", help="COLMAP model folder of held-out cameras (orange)")
    p.add_argument("--seed-ply", dest="seed_ply", help="the seed point cloud (PLY) the model was trained from, to toggle against it")
    p.add_argument("--background", default=None,
                   help="colour behind the Gaussians, RGB in [0,1], e.g. 1,1,1 (default: the one the model was "
                        "trained against, from the train.json beside it; black without one)")
    p.add_argument("--host", default=DEFAULT_HOST, help=f"address to bind (default {DEFAULT_HOST}: this machine only)")
    p.add_argument("--port", type=int, default=DEFAULT_PORT, help=f"port (default {DEFAULT_PORT}; 0 picks a free one)")
    p.add_argument("--timeout", type=float, default=IDLE_TIMEOUT_S,
                   help=f"seconds a connection may stay silent, or take to send its request, before it is closed "
                        f"(default {IDLE_TIMEOUT_S:g}); "
                        f"at most {MAX_CONNECTIONS} connections are answered at once")
    p.add_argument("--no-browser", action="store_true", dest="no_browser", help="do not open a browser")
    p.add_argument("-v", "--verbose", action="count", default=0, help="more log output (repeatable)")
    p.add_argument("-q", "--quiet", action="store_true", help="warnings and errors only")
    return p


LOOPBACK_HOSTS = ("127.0.0.1", "localhost", "::1")


def _stop(signum, frame):
    raise KeyboardInterrupt


def view_background(model: str, flag: str | None) -> tuple[tuple[float, float, float], str]:
    """The colour the view clears to and where it came from: ``--background`` (``flag``,
    ``R,G,B`` in [0, 1]) when given, else the one the model was trained against
    (:func:`splat_train.export.model_background`: its train.json's path, or "default" for black).
    ValueError for a malformed flag."""
    from splat_train.export import model_background, parse_background

    return model_background(model) if flag is None else (parse_background(flag), "--background")


def main(argv: list[str]) -> int:
    """Serve the view until Ctrl-C, SIGTERM or SIGHUP (a quiet stop, exit 0). Bad input (a
    --model that is not a model of its suffix's type (.ply, .splat, .spz) nor a folder, gsply
    missing for a .spz, a port outside 0-65535, a --timeout that is
    not a positive number, an address that cannot be bound) is one line and exit 2."""
    import signal

    args = parser().parse_args(deprecated_flags(argv, "python -m splat_train view", {"--seed": ("--seed-ply", None)}))
    from runtime.logs import setup_logging

    setup_logging(args.verbose, args.quiet)
    from pathlib import Path

    from splat_train.view.server import (ViewerNotInstalled, build_routes, cameras_json, check_installed,
                                         make_server)
    from splat_train.view.source import TYPE_NAMES, ModelSource, UnknownModelType, follow, read_checked
    try:
        check_installed()
    except ViewerNotInstalled as e:
        print(f"python -m splat_train view: error: {e}", file=sys.stderr)
        return 2
    if not 0 <= args.port <= 65535:
        print(f"python -m splat_train view: error: --port {args.port} is not a port: give 1-65535 (0 picks a free one)",
              file=sys.stderr)
        return 2
    if not (args.timeout > 0 and args.timeout < float("inf")):
        print(f"python -m splat_train view: error: --timeout {args.timeout:g} is not a number of seconds > 0",
              file=sys.stderr)
        return 2
    from camio.ply import PlyFormatError
    from camio.splatfmt import SplatFormatError, SpzUnavailable
    from splat_train.export import background_note

    if not (Path(args.model).is_file() or Path(args.model).is_dir()):
        print(f"python -m splat_train view: error: --model {args.model}: no such file or folder", file=sys.stderr)
        return 2
    if args.seed_ply is not None and not Path(args.seed_ply).is_file():
        print(f"python -m splat_train view: error: --seed-ply {args.seed_ply}: no such file", file=sys.stderr)
        return 2
    # only the bytes checked here are ever served (never a link to some other file, nor a file
    # swapped after the check): read once, checked, kept in memory
    try:
        source, seed = ModelSource(args.model), None
    except UnknownModelType as e:
        print(f"python -m splat_train view: error: --model {e}", file=sys.stderr)
        return 2
    label, path, kind = "--model", args.model, source.kind
    try:
        source.refresh(strict=True)
        if args.seed_ply is not None:
            label, path, kind = "--seed-ply", args.seed_ply, "ply"
            seed = read_checked(path)
    except SpzUnavailable as e:
        print(f"python -m splat_train view: error: --model {path}: {e}", file=sys.stderr)
        return 2
    except SplatFormatError as e:  # its message names the file and says it is not one
        print(f"python -m splat_train view: error: --model {e}", file=sys.stderr)
        return 2
    except (PlyFormatError, OSError, ValueError) as e:
        print(f"python -m splat_train view: error: {label} {path} is not a {TYPE_NAMES[kind]}: {e}", file=sys.stderr)
        return 2
    try:
        background, bg_from = view_background(str(source.candidates()[-1]), args.background)
    except ValueError as e:
        print(f"python -m splat_train view: error: {e}", file=sys.stderr)
        return 2
    try:
        blob = cameras_json(args.cameras, args.test_cameras)
    except (OSError, ValueError) as e:
        print(f"python -m splat_train view: error: cannot read the cameras: {e}", file=sys.stderr)
        return 2
    try:
        srv = make_server(build_routes(source, seed, blob, background), args.host, args.port, args.timeout)
    except OSError as e:  # in use, no permission, an address this machine does not have
        if e.errno == errno.EADDRINUSE:
            print(f"python -m splat_train view: error: port {args.port} on {args.host} is already in use "
                  "(another viewer?); pass --port 0 to pick a free one", file=sys.stderr)
        else:
            print(f"python -m splat_train view: error: cannot listen on {args.host}:{args.port}: {e.strerror or e}",
                  file=sys.stderr)
        return 2
    if args.host not in LOOPBACK_HOSTS:
        print(f"python -m splat_train view: warning: --host {args.host} serves the model to the network (no password); "
              "the default 127.0.0.1 keeps it on this machine", file=sys.stderr, flush=True)
    host = f"[{args.host}]" if ":" in args.host else args.host
    url = f"http://{host}:{srv.server_port}/"
    now = source.current()
    what = args.model if not source.folder else (
        f"the training run {args.model} live ({(now.path if now else source.candidates()[0]).name}"
        f"{'' if now is None or now.iteration is None else f' at iteration {now.iteration}'}, "
        "reloaded when it changes)")
    print(f"[view] serving {what} at {url} on {background_note(background, bg_from)}; Ctrl-C stops",
          flush=True)
    if source.current() is None:
        print(f"[view] waiting for {source.candidates()[0]} (train with --snapshot-every N)", flush=True)
    # after pycolmap is loaded (cameras_json): its crash handler must not answer SIGTERM. SIGINT
    # too: a process started in the background by a non-interactive shell (`cmd &`) inherits
    # SIGINT ignored, and Python then installs no Ctrl-C handler of its own
    for signum in (signal.SIGTERM, signal.SIGHUP, signal.SIGINT):
        signal.signal(signum, _stop)
    if not args.no_browser:
        webbrowser.open(url)
    stop = threading.Event()
    follow(source, stop)
    try:
        srv.serve_forever()
    except KeyboardInterrupt:
        print("[view] stopped", flush=True)
    finally:
        stop.set()
        srv.server_close()
    return 0
