"""Headless Chromium driven over the DevTools protocol with the standard library only.

Used by the browser test and the open-time benchmark: start Chromium with software WebGL
(SwiftShader), open a URL, wait for a JavaScript condition, take a PNG screenshot. The
websocket client implements just what DevTools needs (RFC 6455 text frames, client masking).
"""

from __future__ import annotations

import base64
import json
import os
import shutil
import socket
import struct
import subprocess
import tempfile
import time
import urllib.request
from pathlib import Path

CHROMIUM_NAMES = ("chromium", "chromium-browser", "google-chrome", "chrome")
# software WebGL2 that runs on any CPU machine
CHROMIUM_FLAGS = ("--headless=new", "--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
                  "--ignore-gpu-blocklist", "--force-device-scale-factor=1", "--hide-scrollbars",
                  "--no-first-run", "--no-default-browser-check", "--disable-extensions",
                  "--disable-background-timer-throttling", "--disable-renderer-backgrounding")


def find_chromium() -> str | None:
    env = os.environ.get("CHROMIUM")
    if env:
        return env
    for n in CHROMIUM_NAMES:
        if p := shutil.which(n):
            return p
    return None


class _WebSocket:
    def __init__(self, url: str, timeout: float):
        assert url.startswith("ws://")
        hostport, _, path = url[5:].partition("/")
        host, _, port = hostport.partition(":")
        self.sock = socket.create_connection((host, int(port)), timeout=timeout)
        key = base64.b64encode(os.urandom(16)).decode()
        self.sock.sendall((f"GET /{path} HTTP/1.1\r\nHost: {hostport}\r\nUpgrade: websocket\r\n"
                           f"Connection: Upgrade\r\nSec-WebSocket-Key: {key}\r\n"
                           "Sec-WebSocket-Version: 13\r\n\r\n").encode())
        head = b""
        while b"\r\n\r\n" not in head:
            chunk = self.sock.recv(4096)
            if not chunk:
                raise ConnectionError("DevTools closed the connection during the handshake")
            head += chunk
        if b" 101 " not in head.split(b"\r\n", 1)[0]:
            raise ConnectionError(f"DevTools refused the websocket: {head[:200]!r}")
        self.buf = head.split(b"\r\n\r\n", 1)[1]

    def _read(self, n: int) -> bytes:
        while len(self.buf) < n:
            chunk = self.sock.recv(1 << 20)
            if not chunk:
                raise ConnectionError("DevTools closed the connection")
            self.buf += chunk
        out, self.buf = self.buf[:n], self.buf[n:]
        return out

    def send(self, text: str) -> None:
        data = text.encode()
        n = len(data)
        head = bytes([0x81])
        if n < 126:
            head += bytes([0x80 | n])
        elif n < 1 << 16:
            head += bytes([0x80 | 126]) + struct.pack(">H", n)
        else:
            head += bytes([0x80 | 127]) + struct.pack(">Q", n)
        mask = os.urandom(4)
        self.sock.sendall(head + mask + bytes(b ^ mask[i % 4] for i, b in enumerate(data)))

    def recv(self) -> str:
        parts = []
        while True:
            b0, b1 = self._read(2)
            n = b1 & 0x7F
            if n == 126:
                n = struct.unpack(">H", self._read(2))[0]
            elif n == 127:
                n = struct.unpack(">Q", self._read(8))[0]
            payload = self._read(n)
            op = b0 & 0x0F
            if op == 0x8:
                raise ConnectionError("DevTools closed the websocket")
            if op in (0x9, 0xA):  # ping/pong: not expected from DevTools; ignore
                continue
            parts.append(payload)
            if b0 & 0x80:
                return b"".join(parts).decode()

    def close(self) -> None:
        self.sock.close()


class Chromium:
    """One headless Chromium with one page; ``with Chromium(width, height) as c: c.open(url)``."""

    def __init__(self, width: int = 1024, height: int = 768, binary: str | None = None, timeout: float = 120.0):
        self.binary = binary or find_chromium()
        if self.binary is None:
            raise FileNotFoundError("no Chromium found (Debian: apt-get install chromium; or set CHROMIUM)")
        self.width, self.height, self.timeout = width, height, timeout
        self._id = 0

    def __enter__(self) -> "Chromium":
        self.profile = tempfile.mkdtemp(prefix="chromium-view-")
        self.proc = subprocess.Popen(
            [self.binary, *CHROMIUM_FLAGS, f"--window-size={self.width},{self.height}",
             f"--user-data-dir={self.profile}", "--remote-debugging-port=0", "about:blank"],
            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        port_file = Path(self.profile) / "DevToolsActivePort"
        t0 = time.monotonic()
        while not port_file.is_file() or not port_file.read_text().strip():
            if self.proc.poll() is not None:
                raise RuntimeError(f"Chromium exited: {self.proc.stderr.read().decode(errors='replace')[-2000:]}")
            if time.monotonic() - t0 > 60:
                raise TimeoutError("Chromium did not open its DevTools port in 60 s")
            time.sleep(0.1)
        port = int(port_file.read_text().split()[0])
        t0 = time.monotonic()
        while True:
            try:
                targets = json.load(urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=10))
                page = next(t for t in targets if t.get("type") == "page")
                break
            except (OSError, StopIteration):
                if time.monotonic() - t0 > 30:
                    raise
                time.sleep(0.2)
        self.ws = _WebSocket(page["webSocketDebuggerUrl"], self.timeout)
        self.call("Emulation.setDeviceMetricsOverride",
                  width=self.width, height=self.height, deviceScaleFactor=1, mobile=False)
        self.call("Runtime.enable")
        return self

    def __exit__(self, *exc) -> None:
        try:
            self.ws.close()
        except Exception:
            pass
        self.proc.terminate()
        try:
            self.proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        shutil.rmtree(self.profile, ignore_errors=True)

    def call(self, method: str, **params) -> dict:
        self._id += 1
        my = self._id
        self.ws.send(json.dumps({"id": my, "method": method, "params": params}))
        while True:
            msg = json.loads(self.ws.recv())
            if msg.get("id") == my:
                if "error" in msg:
                    raise RuntimeError(f"{method}: {msg['error']}")
                return msg.get("result", {})
            if msg.get("method") == "Runtime.exceptionThrown":
                self.last_exception = msg["params"]

    def evaluate(self, expression: str):
        r = self.call("Runtime.evaluate", expression=expression, returnByValue=True)
        return r.get("result", {}).get("value")

    def open(self, url: str) -> None:
        self.call("Page.navigate", url=url)

    def wait_for(self, expression: str, timeout: float | None = None, error_expression: str | None = None) -> float:
        """Poll ``expression`` until truthy; returns the seconds waited. Raises with the page's error."""
        t0 = time.monotonic()
        limit = self.timeout if timeout is None else timeout
        while True:
            if self.evaluate(expression):
                return time.monotonic() - t0
            if error_expression and (err := self.evaluate(error_expression)):
                raise RuntimeError(f"page error: {err}")
            if time.monotonic() - t0 > limit:
                raise TimeoutError(f"{expression!r} still false after {limit:.0f} s")
            time.sleep(0.1)

    def screenshot(self, path: str | Path, width: int | None = None, height: int | None = None) -> Path:
        clip = {"x": 0, "y": 0, "width": width or self.width, "height": height or self.height, "scale": 1}
        data = self.call("Page.captureScreenshot", format="png", clip=clip)["data"]
        Path(path).write_bytes(base64.b64decode(data))
        return Path(path)
