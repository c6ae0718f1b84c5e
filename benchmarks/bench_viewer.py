"""How long a 200k-Gaussian model takes to open in the browser viewer (headless Chromium,
software WebGL). Prints the time from navigation to the model loaded (``viewerLoadMs``: PLY
fetched, parsed and uploaded) and to the view settled (sorted and drawn, ``viewerReady``).

    python benchmarks/bench_viewer.py [--gaussians 200000] [--size 640x480]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

from _view_scene import make_cameras, make_model  # noqa: E402
from camio.colmap import write_text_model  # noqa: E402
from camio.ply import write_gaussian_ply  # noqa: E402
from runtime.cliargs import plain
from splat_train.view import server  # noqa: E402
from splat_train.view.headless import Chromium  # noqa: E402


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=plain(__doc__.split("\n\n")[0]))
    p.add_argument("--gaussians", type=int, default=200_000)
    p.add_argument("--size", default="640x480", help="window and camera size WxH")
    args = p.parse_args(argv)
    w, h = (int(v) for v in args.size.split("x"))
    server.check_installed()
    with tempfile.TemporaryDirectory() as tmp:
        model = write_gaussian_ply(Path(tmp) / "model.ply", make_model(args.gaussians, sh_degree=3))
        cams = write_text_model(Path(tmp) / "train", make_cameras(w, h, 4))
        size_mb = model.stat().st_size / 1e6
        srv = server.make_server(server.build_routes(model, None, server.cameras_json(cams)), port=0)
        server.serve_in_thread(srv)
        try:
            with Chromium(w, h, timeout=600) as browser:
                t0 = time.perf_counter()
                browser.open(f"http://127.0.0.1:{srv.server_port}/?camera=view00.png&ui=0")
                browser.wait_for("window.viewerReady", timeout=600, error_expression="window.viewerError")
                wall = time.perf_counter() - t0
                load_ms = browser.evaluate("window.viewerLoadMs")
        finally:
            srv.shutdown()
            srv.server_close()
    print(f"viewer open, {args.gaussians} Gaussians (SH 3, {size_mb:.0f} MB PLY), {w}x{h}, headless Chromium "
          f"SwiftShader: model loaded {load_ms / 1000:.2f} s after navigation, view settled {wall:.2f} s "
          f"(wall, includes the page's 0.3-0.5 s settle wait)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
