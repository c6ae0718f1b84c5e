"""A read-only local HTTP server for one view: a fixed table of URL -> file, nothing else.

Only the URLs in the table are answered (GET/HEAD); every other path, including ``..``,
absolute, encoded or symlinked variants, gets 404 without touching the file system, since the
request path is never joined to a folder. Binds 127.0.0.1 unless told otherwise.

A request is answered only if its ``Host`` header names this server: ``localhost``,
``127.0.0.1``, ``[::1]``, or the very address the connection arrived at, with the server's
port (:func:`host_allowed`). A web page the user visits cannot read the model through DNS
rebinding: its requests carry the attacker's domain name as Host and get 403.
"""

from __future__ import annotations

import json
import logging
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import numpy as np

from runtime.view_defaults import VIEW_HOST, VIEW_PORT

log = logging.getLogger("splat_train.view")

DEFAULT_HOST = VIEW_HOST
DEFAULT_PORT = VIEW_PORT
STATIC_DIR = Path(__file__).resolve().parent / "static"
NPM_DIR = Path(__file__).resolve().parent / "npm"
NODE_MODULES = NPM_DIR / "node_modules"
# URL -> file under node_modules: the ES modules the page imports (see static/index.html's importmap).
VENDOR_FILES = {
    "/vendor/three.module.js": "three/build/three.module.js",
    "/vendor/three.core.js": "three/build/three.core.js",
    "/vendor/three-addons/postprocessing/Pass.js": "three/examples/jsm/postprocessing/Pass.js",
    "/vendor/three-addons/controls/OrbitControls.js": "three/examples/jsm/controls/OrbitControls.js",
    "/vendor/spark.module.js": "@sparkjsdev/spark/dist/spark.module.js",
}
STATIC_FILES = {"/": "index.html", "/index.html": "index.html", "/viewer.js": "viewer.js", "/shfix.js": "shfix.js"}
CONTENT_TYPES = {".js": "text/javascript; charset=utf-8", ".html": "text/html; charset=utf-8",
                 ".json": "application/json", ".ply": "application/octet-stream"}
INSTALL_HINT = ("the viewer's browser libraries are not installed: run `make install` "
                "(or `npm ci --prefix splat_train/view/npm`)")


class ViewerNotInstalled(RuntimeError):
    pass


def check_installed() -> None:
    missing = [rel for rel in VENDOR_FILES.values() if not (NODE_MODULES / rel).is_file()]
    if missing:
        raise ViewerNotInstalled(f"{INSTALL_HINT}; missing {NODE_MODULES / missing[0]}")


def camera_record(cam, role: str) -> dict:
    """One camera for the page: OpenCV cam_from_world, K (COLMAP pixels), size, role."""
    return {"name": cam.name, "role": role, "width": cam.width, "height": cam.height,
            "K": np.asarray(cam.K, dtype=float).tolist(),
            "cam_from_world": np.asarray(cam.cam_from_world, dtype=float).tolist()}


def cameras_json(cameras: str | Path | None = None, test_cameras: str | Path | None = None) -> bytes:
    """The view's ``cameras.json``: training (``--cameras``) then held-out (``--test-cameras``)."""
    from camio.colmap import read_model

    recs = []
    for folder, role in ((cameras, "train"), (test_cameras, "test")):
        if folder is not None:
            recs += [camera_record(c, role) for c in read_model(folder, allow_distorted=True).cameras]
    return json.dumps({"cameras": recs}).encode()


def build_routes(model: str | Path, seed: str | Path | None = None, cameras_blob: bytes | None = None,
                 background: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> dict[str, Path | bytes]:
    """The complete table of what the server answers: URL path -> file or bytes. ``background``:
    RGB in [0, 1] the page clears to, behind the Gaussians (the colour the model was trained
    against: a model trained against a colour is transparent where that colour was)."""
    routes: dict[str, Path | bytes] = {url: STATIC_DIR / rel for url, rel in STATIC_FILES.items()}
    routes.update({url: NODE_MODULES / rel for url, rel in VENDOR_FILES.items()})
    routes["/model.ply"] = Path(model).resolve()
    if seed is not None:
        routes["/seed.ply"] = Path(seed).resolve()
    routes["/cameras.json"] = cameras_blob if cameras_blob is not None else b'{"cameras": []}'
    routes["/view.json"] = json.dumps({"seed": seed is not None,
                                       "background": [float(x) for x in background]}).encode()
    return routes


LOOPBACK_NAMES = ("localhost", "127.0.0.1", "::1")


def host_allowed(host_header: str | None, local_ip: str, port: int) -> bool:
    """Whether a request's ``Host`` header names this server (module docstring): a loopback
    name, or ``local_ip`` (the address the connection arrived at), with ``port`` when a port
    is given (the default port 80 is never this server's)."""
    if not host_header:
        return False
    h = host_header.strip().lower()
    if h.startswith("["):  # [v6]:port
        name, _, rest = h[1:].partition("]")
        port_s = rest[1:] if rest.startswith(":") else None
        if rest and not rest.startswith(":"):
            return False
    elif h.count(":") == 1:
        name, _, port_s = h.partition(":")
    else:
        name, port_s = h, None
    if port_s is None:
        if port != 80:
            return False
    elif not port_s.isdigit() or int(port_s) != port:
        return False
    local = local_ip.lower()
    if local.startswith("::ffff:"):
        local = local[7:]
    return name in LOOPBACK_NAMES or name == local


class _Handler(BaseHTTPRequestHandler):
    routes: dict[str, Path | bytes] = {}
    server_version = "splat_train-view"

    def log_message(self, fmt, *args):  # quiet by default; -v shows requests
        log.debug("%s " + fmt, self.address_string(), *args)

    def _lookup(self) -> tuple[Path | bytes | None, str]:
        path = self.path.split("?", 1)[0].split("#", 1)[0]
        # exact match only: no decoding, no joining, no normalisation
        return self.routes.get(path), path

    def _send(self, head_only: bool) -> None:
        if not host_allowed(self.headers.get("Host"), self.connection.getsockname()[0], self.server.server_port):
            log.warning("refused a request for Host %r (only this server's own address or localhost is "
                        "answered)", self.headers.get("Host"))
            self.send_error(403, "Host not served: use this server's address or localhost")
            return
        target, path = self._lookup()
        if target is None:
            self.send_error(404, "not part of this view")
            return
        ext = Path(path if path != "/" else "/index.html").suffix
        ctype = CONTENT_TYPES.get(ext, "application/octet-stream")
        if isinstance(target, bytes):
            data, size = target, len(target)
        else:
            try:
                size = target.stat().st_size
            except OSError:
                self.send_error(404, "file missing")
                return
            data = None
        self.send_response(200)
        self.send_header("Content-Type", ctype)
        self.send_header("Content-Length", str(size))
        self.send_header("Cache-Control", "no-store")
        self.send_header("X-Content-Type-Options", "nosniff")
        self.end_headers()
        if head_only:
            return
        if data is not None:
            self.wfile.write(data)
            return
        with open(target, "rb") as f:
            while chunk := f.read(1 << 20):
                self.wfile.write(chunk)

    def do_GET(self):
        self._send(False)

    def do_HEAD(self):
        self._send(True)

    def _refuse(self):
        self.send_error(405, "read-only")

    do_POST = do_PUT = do_DELETE = do_PATCH = do_OPTIONS = _refuse


def make_server(routes: dict[str, Path | bytes], host: str = DEFAULT_HOST, port: int = DEFAULT_PORT
                ) -> ThreadingHTTPServer:
    """A server answering only ``routes`` (port 0 picks a free one; ``server.server_port``)."""
    handler = type("ViewHandler", (_Handler,), {"routes": dict(routes)})
    srv = ThreadingHTTPServer((host, port), handler)
    srv.daemon_threads = True
    return srv


def serve_in_thread(srv: ThreadingHTTPServer) -> threading.Thread:
    t = threading.Thread(target=srv.serve_forever, daemon=True)
    t.start()
    return t
