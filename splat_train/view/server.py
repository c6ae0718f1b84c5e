"""A read-only local HTTP server for one view: a fixed table of URL -> file, nothing else.

Only the URLs in the table are answered (GET/HEAD); every other path, including ``..``,
absolute, encoded or symlinked variants, gets 404 without touching the file system, since the
request path is never joined to a folder. Binds 127.0.0.1 unless told otherwise.

A request is answered only if its ``Host`` header names this server: ``localhost``,
``127.0.0.1``, ``[::1]``, or the very address the connection arrived at, with the server's
port (:func:`host_allowed`). A web page the user visits cannot read the model through DNS
rebinding: its requests carry the attacker's domain name as Host and get 403.

Bounded: at most :data:`MAX_CONNECTIONS` connections are handled at once, one thread each; one
more is answered 503 by the accepting thread and closed, without a thread. A connection that
sends or takes nothing for ``timeout`` seconds (:data:`IDLE_TIMEOUT_S` unless told) is closed,
and so is one whose request is not complete ``timeout`` seconds after it connected (a client
that trickles a byte at a time holds no thread longer).
A client that goes away mid-answer (a browser that stops a download: ``BrokenPipeError``,
``ConnectionResetError``) costs one debug line, never a traceback.

The model is served at ``/model.<type>`` (``/model.ply``, ``/model.splat`` or ``/model.spz``:
its file's type, :func:`.source.model_type`) from memory, the bytes that were checked
(:mod:`.source`), with the headers ``X-Model-Version`` and ``X-Model-Iteration`` (empty for a
model without an iteration); ``/state.json`` says which version is served now, and its type.
"""

from __future__ import annotations

import io
import json
import logging
import socket
import sys
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Callable, Union

import numpy as np

from runtime.view_defaults import VIEW_HOST, VIEW_PORT
from splat_train.view.source import ModelSource, read_checked

log = logging.getLogger("splat_train.view")

DEFAULT_HOST = VIEW_HOST
DEFAULT_PORT = VIEW_PORT
MAX_CONNECTIONS = 16  # handler threads at once (a browser opens 6 per server)
IDLE_TIMEOUT_S = 30.0  # a connection silent this long (reading or writing) is closed
# what a client that went away raises mid-answer: one debug line, no traceback
CLIENT_GONE = (BrokenPipeError, ConnectionResetError, ConnectionAbortedError, TimeoutError)
_BUSY_BODY = b"viewer busy: retry.\r\n"
BUSY_REPLY = (b"HTTP/1.0 503 Service Unavailable\r\nContent-Type: text/plain\r\nContent-Length: "
              + str(len(_BUSY_BODY)).encode() + b"\r\nRetry-After: 1\r\nConnection: close\r\n\r\n" + _BUSY_BODY)
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
# the three model types are binary formats with no registered media type (a .spz is a gzip stream,
# but not one a browser should unpack: Spark reads the stream itself)
CONTENT_TYPES = {".js": "text/javascript; charset=utf-8", ".html": "text/html; charset=utf-8",
                 ".json": "application/json", ".ply": "application/octet-stream",
                 ".splat": "application/octet-stream", ".spz": "application/octet-stream"}
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


# a route's answer made at request time: (body, extra headers), or None for 503 (not ready)
Dynamic = Callable[[], "tuple[bytes, dict[str, str]] | None"]
Route = Union[Path, bytes, Dynamic]


def model_route(source: ModelSource) -> Dynamic:
    """``/model.<type>``: the bytes ``source`` serves now, with their version and iteration."""
    def answer() -> tuple[bytes, dict[str, str]] | None:
        s = source.current()
        if s is None:
            return None
        return s.data, {"X-Model-Version": str(s.version),
                        "X-Model-Iteration": "" if s.iteration is None else str(s.iteration)}
    return answer


def model_url(source: ModelSource) -> str:
    """The URL the model of ``source`` is served at: ``/model.`` and its type."""
    return f"/model.{source.kind}"


def build_routes(model: ModelSource | str | Path, seed: bytes | str | Path | None = None,
                 cameras_blob: bytes | None = None,
                 background: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> dict[str, Route]:
    """The complete table of what the server answers: URL path -> file, bytes or answer made at
    request time. ``model``: what ``/model.<type>`` serves (:mod:`.source`; a path is read and
    checked now); ``seed``: the seed PLY's checked bytes (a path is read and checked now).
    ``background``: RGB in [0, 1] the page clears to, behind the Gaussians (the colour the model
    was trained against: a model trained against a colour is transparent where that colour was).
    PlyFormatError / SplatFormatError / OSError for a path that is not a model of its type
    (UnknownModelType for a suffix that is none)."""
    if not isinstance(model, ModelSource):
        model = ModelSource(model)
        model.refresh(strict=True)
    if seed is not None and not isinstance(seed, bytes):
        seed = read_checked(seed)
    routes: dict[str, Route] = {url: STATIC_DIR / rel for url, rel in STATIC_FILES.items()}
    routes.update({url: NODE_MODULES / rel for url, rel in VENDOR_FILES.items()})
    routes[model_url(model)] = model_route(model)
    routes["/state.json"] = lambda: (model.state_json(), {})
    if seed is not None:
        routes["/seed.ply"] = bytes(seed)
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


class _DeadlineReader(io.RawIOBase):
    """A socket's reads that fail (TimeoutError) once ``deadline`` (time.monotonic) has passed,
    each waiting at most ``timeout`` seconds."""

    def __init__(self, sock: socket.socket, timeout: float, deadline: float):
        self.sock, self.timeout, self.deadline = sock, timeout, deadline

    def readable(self) -> bool:
        return True

    def readinto(self, buf) -> int:
        left = self.deadline - time.monotonic()
        if left <= 0:
            raise TimeoutError("the request was not complete in time")
        self.sock.settimeout(min(self.timeout, left))
        return self.sock.recv_into(buf)


class _Handler(BaseHTTPRequestHandler):
    routes: dict[str, Route] = {}
    server_version = "splat_train-view"
    timeout = IDLE_TIMEOUT_S  # the socket's timeout (StreamRequestHandler.setup)

    def setup(self) -> None:
        super().setup()  # the socket's timeout; rfile and wfile
        self.rfile.close()  # its own reader, replaced (closed, so that closing the socket closes it)
        self.rfile = io.BufferedReader(_DeadlineReader(self.connection, self.timeout,
                                                       time.monotonic() + self.timeout))

    def log_message(self, fmt, *args):  # quiet by default; -v shows requests
        log.debug("%s " + fmt, self.address_string(), *args)

    def _lookup(self) -> tuple[Route | None, str]:
        path = self.path.split("?", 1)[0].split("#", 1)[0]
        # exact match only: no decoding, no joining, no normalisation
        return self.routes.get(path), path

    def _send(self, head_only: bool) -> None:
        self.connection.settimeout(self.timeout)  # the request is in: the answer's own timeout
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
        extra: dict[str, str] = {}
        if callable(target):
            answer = target()
            if answer is None:
                self.send_error(503, "no model yet: waiting for the training run's first snapshot")
                return
            target, extra = answer
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
        for k, v in extra.items():
            self.send_header(k, v)
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


class _Slot:
    """One connection's hold on the server's semaphore, given back once whoever gives it back."""

    def __init__(self, sem: threading.BoundedSemaphore):
        self._sem = sem
        self._lock = threading.Lock()
        self._held = True

    def release(self) -> None:
        with self._lock:
            if self._held:
                self._held = False
                self._sem.release()


class ViewServer(ThreadingHTTPServer):
    """A thread per connection, at most ``max_connections`` at once (module docstring)."""

    daemon_threads = True

    def __init__(self, address: tuple[str, int], handler: type, max_connections: int = MAX_CONNECTIONS):
        self.max_connections = max_connections
        self.slots = threading.BoundedSemaphore(max_connections)
        self._slot_of: dict[object, _Slot] = {}  # request -> its slot, until its thread takes it
        super().__init__(address, handler)

    def process_request(self, request, client_address) -> None:
        if not self.slots.acquire(blocking=False):  # full: answer here, in the accepting thread
            log.debug("busy (%d connections): 503 to %s", self.max_connections, client_address[0])
            try:
                request.settimeout(1.0)
                request.sendall(BUSY_REPLY)
            except OSError:
                pass
            self.shutdown_request(request)
            return
        slot = self._slot_of[request] = _Slot(self.slots)
        try:
            super().process_request(request, client_address)
        except BaseException:
            # No thread, or a stop arrived while Thread.start() waited for one that has already run
            # and given the slot back: either way the slot is given back once, and the stop goes on.
            self._slot_of.pop(request, None)
            slot.release()
            raise

    def process_request_thread(self, request, client_address) -> None:
        slot = self._slot_of.pop(request, None)
        try:
            super().process_request_thread(request, client_address)
        except BaseException as exc:  # noqa: BLE001 - a handler thread ends in one log line, never a
            # traceback (one escaped while the viewer was being stopped under load)
            log.debug("the connection of %s ended: %s: %s", client_address[0], type(exc).__name__, exc)
        finally:
            if slot is not None:
                slot.release()

    def handle_error(self, request, client_address) -> None:
        exc = sys.exc_info()[1]
        if isinstance(exc, CLIENT_GONE):
            log.debug("%s went away: %s", client_address[0], exc)
            return
        log.error("answering %s failed: %s: %s", client_address[0], type(exc).__name__, exc)
        log.debug("traceback", exc_info=True)


def make_server(routes: dict[str, Route], host: str = DEFAULT_HOST, port: int = DEFAULT_PORT,
                timeout: float = IDLE_TIMEOUT_S) -> ViewServer:
    """A server answering only ``routes`` (port 0 picks a free one; ``server.server_port``);
    ``timeout``: seconds a connection may stay silent."""
    handler = type("ViewHandler", (_Handler,), {"routes": dict(routes), "timeout": float(timeout)})
    return ViewServer((host, port), handler)


def serve_in_thread(srv: ThreadingHTTPServer) -> threading.Thread:
    t = threading.Thread(target=srv.serve_forever, daemon=True)
    t.start()
    return t
