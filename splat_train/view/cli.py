"""``python -m splat_train view``: serve one trained model (and its cameras) to a browser."""

from __future__ import annotations

import argparse
import logging
import sys
import webbrowser

from splat_train.view.server import DEFAULT_HOST, DEFAULT_PORT

log = logging.getLogger("splat_train.view")


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m splat_train view",
        description="Show a trained 3DGS PLY in the browser (Spark on three.js, installed by `make install`), "
                    "with its cameras as frusta; pick a camera to look through it. Serves only these files, "
                    "read-only, on a local port.")
    p.add_argument("--model", required=True, help="the trained model.ply (3DGS layout)")
    p.add_argument("--cameras", help="COLMAP model folder of the training cameras (drawn green)")
    p.add_argument("--test-cameras", dest="test_cameras", help="COLMAP model folder of held-out cameras (orange)")
    p.add_argument("--seed", help="the seed PLY, to toggle against the trained model")
    p.add_argument("--host", default=DEFAULT_HOST, help=f"address to bind (default {DEFAULT_HOST}: this machine only)")
    p.add_argument("--port", type=int, default=DEFAULT_PORT, help=f"port (default {DEFAULT_PORT}; 0 picks a free one)")
    p.add_argument("--no-browser", action="store_true", dest="no_browser", help="do not open a browser")
    return p


def main(argv: list[str]) -> int:
    args = parser().parse_args(argv)
    from pathlib import Path

    from splat_train.view.server import (ViewerNotInstalled, build_routes, cameras_json, check_installed,
                                         make_server)
    try:
        check_installed()
    except ViewerNotInstalled as e:
        print(f"splat_train view: {e}", file=sys.stderr)
        return 2
    for label, path in (("--model", args.model), ("--seed", args.seed)):
        if path is not None and not Path(path).is_file():
            print(f"splat_train view: {label} {path}: no such file", file=sys.stderr)
            return 2
    blob = cameras_json(args.cameras, args.test_cameras)
    srv = make_server(build_routes(args.model, args.seed, blob), args.host, args.port)
    url = f"http://{args.host}:{srv.server_port}/"
    print(f"[view] serving {args.model} at {url} (Ctrl-C stops)", flush=True)
    if not args.no_browser:
        webbrowser.open(url)
    try:
        srv.serve_forever()
    except KeyboardInterrupt:
        pass
    finally:
        srv.server_close()
    return 0
