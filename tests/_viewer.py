"""``python -m splat_train view`` started the way a user starts it, for the viewer's CLI tests."""

from __future__ import annotations

import http.client
import os
import subprocess
import sys

import pytest

from _cli import ENV, ROOT
from splat_train.view import server


class Viewer:
    """The viewer as a user starts it (``--port 0 --no-browser``), stopped by SIGTERM."""

    def __init__(self, *args: str):
        try:
            server.check_installed()
        except server.ViewerNotInstalled as e:
            pytest.skip(str(e))
        self.proc = subprocess.Popen([sys.executable, "-m", "splat_train", "view", "--no-browser", "--port", "0",
                                      *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                     cwd=ROOT, env=ENV)
        self.line = line = self.proc.stdout.readline()  # the command's first line: what it serves, where
        assert "http://127.0.0.1:" in line, (line, self.stop()[1])
        self.port = int(line.split("http://127.0.0.1:")[1].split("/")[0])

    def get(self, path: str = "/model.ply") -> http.client.HTTPResponse:
        conn = http.client.HTTPConnection("127.0.0.1", self.port, timeout=20)
        conn.request("GET", path)
        r = conn.getresponse()
        r.body = r.read()
        conn.close()
        return r

    def threads(self) -> int:
        return len(os.listdir(f"/proc/{self.proc.pid}/task"))

    def stop(self) -> tuple[str, str]:
        if self.proc.poll() is None:
            self.proc.terminate()
        try:
            out, err = self.proc.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            out, err = self.proc.communicate()
        return out, err
