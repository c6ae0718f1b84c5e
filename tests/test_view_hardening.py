"""``python -m splat_train view`` under hostile clients and a hostile file system, through the
command a user runs: an idle connection is closed after ``--timeout``; a browser that stops a
download leaves no traceback; more connections than ``MAX_CONNECTIONS`` get 503 and no thread;
a model file swapped after the start is checked again and served only if it is a 3DGS PLY."""

from __future__ import annotations

import os
import socket
import struct
import time

import pytest

from _view_scene import make_model, write_view_scene
from _viewer import Viewer
from camio.ply import write_gaussian_ply
from splat_train.view import server
from splat_train.view.source import FOLLOW_POLL_S


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> dict:
    return write_view_scene(tmp_path_factory.mktemp("view"), n=40, width=32, height=24)


def _connect(port: int) -> socket.socket:
    return socket.create_connection(("127.0.0.1", port), timeout=10)


def test_an_idle_connection_is_closed_after_the_timeout(scene):
    v = Viewer("--model", str(scene["model"]), "--timeout", "1")
    try:
        idle = _connect(v.port)
        t0 = time.monotonic()
        assert idle.recv(1024) == b""  # closed by the server, nothing sent: no request was made
        waited = time.monotonic() - t0
        idle.close()
        assert 0.5 < waited < 8, waited
        assert v.get().status == 200  # the slot it held is free again
    finally:
        _, err = v.stop()
    assert "Traceback" not in err, err


def test_an_aborted_download_leaves_no_traceback(tmp_path):
    model = write_gaussian_ply(tmp_path / "model.ply", make_model(60_000, sh_degree=3))  # ~15 MB
    v = Viewer("--model", str(model))
    try:
        for reset in (True, False, True):
            s = _connect(v.port)
            s.sendall(f"GET /model.ply HTTP/1.1\r\nHost: 127.0.0.1:{v.port}\r\n\r\n".encode())
            assert s.recv(4096).startswith(b"HTTP/1.0 200")
            if reset:  # close with RST at once: the server's next send fails (ConnectionResetError)
                s.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
            s.close()  # else a plain close mid-body: BrokenPipeError
        time.sleep(1.0)
        r = v.get()
        assert r.status == 200 and r.body == model.read_bytes()
    finally:
        _, err = v.stop()
    assert v.proc.returncode == 0, err
    assert "Traceback" not in err and "Error" not in err and "Exception" not in err, err


def test_more_connections_than_the_limit_get_503_and_no_thread(scene):
    v = Viewer("--model", str(scene["model"]), "--timeout", "20")
    held: list[socket.socket] = []
    try:
        assert v.get().status == 200
        time.sleep(0.3)
        before = v.threads()  # main, the follower; no handler thread left
        extra = 6
        held = [_connect(v.port) for _ in range(server.MAX_CONNECTIONS + extra)]
        time.sleep(1.0)
        assert v.threads() <= before + server.MAX_CONNECTIONS, (before, v.threads())
        answered = []
        for s in held:  # the first MAX_CONNECTIONS wait for a request; the others were refused
            s.settimeout(0.3)
            try:
                answered.append(s.recv(1024))
            except TimeoutError:
                answered.append(None)
        busy = [a for a in answered if a is not None]
        assert len(busy) == extra and all(a.startswith(b"HTTP/1.0 503") for a in busy), answered
        for s in held:
            s.close()
        held = []
        deadline = time.monotonic() + 10
        while (r := v.get()).status != 200 and time.monotonic() < deadline:  # slots given back
            time.sleep(0.2)
        assert r.status == 200
    finally:
        for s in held:
            s.close()
        _, err = v.stop()
    assert "Traceback" not in err, err


@pytest.mark.parametrize("swap", ["replaced", "overwritten"])
def test_a_model_swapped_for_garbage_is_not_served(tmp_path, swap):
    files = write_view_scene(tmp_path / "scene", n=30, width=32, height=24)
    model = files["model"]
    good = model.read_bytes()
    v = Viewer("--model", str(model))
    try:
        r = v.get()
        assert r.body == good and r.getheader("X-Model-Version") == "1"
        garbage = b"root:x:0:0:root:/root:/bin/bash\n" * 100
        if swap == "replaced":  # a new file renamed over it
            (tmp_path / "other").write_bytes(garbage)
            os.replace(tmp_path / "other", model)
        else:  # the same file written in place
            model.write_bytes(garbage)
        time.sleep(3 * FOLLOW_POLL_S)
        r = v.get()
        assert r.status == 200 and r.body == good and r.getheader("X-Model-Version") == "1"
        # a valid model put there is checked and served, as a new version
        write_gaussian_ply(model, make_model(12, seed=5))
        deadline = time.monotonic() + 20
        while (r := v.get()).getheader("X-Model-Version") == "1" and time.monotonic() < deadline:
            time.sleep(0.2)
        assert r.body == model.read_bytes() and r.getheader("X-Model-Version") == "2"
    finally:
        _, err = v.stop()
    assert "is not a 3DGS PLY" in err and "still serving the last good model" in err, err
    assert "Traceback" not in err, err


@pytest.mark.parametrize("value", ["0", "-1", "nan", "inf"])
def test_a_timeout_that_is_not_a_positive_number_is_one_line(scene, value):
    from _cli import refused, run

    try:
        server.check_installed()
    except server.ViewerNotInstalled as e:
        pytest.skip(str(e))
    proc = run(["-m", "splat_train", "view", "--model", str(scene["model"]), "--no-browser", "--port", "0",
                "--timeout", value], timeout=60)
    refused(proc, "--timeout")


def test_a_request_trickled_a_byte_at_a_time_is_cut_at_the_timeout(scene):
    """Never silent for ``--timeout`` seconds, yet not complete ``--timeout`` seconds after it
    connected: closed all the same, its thread free again."""
    v = Viewer("--model", str(scene["model"]), "--timeout", "1")
    try:
        s = _connect(v.port)
        t0 = time.monotonic()
        closed = False
        for c in f"GET /model.ply HTTP/1.1\r\nHost: 127.0.0.1:{v.port}\r\nX-Slow: ".encode() + b"a" * 100:
            try:
                s.sendall(bytes([c]))
            except OSError:  # the server closed it
                closed = True
                break
            s.settimeout(0.3)
            try:
                if s.recv(1024) == b"":
                    closed = True
                    break
            except TimeoutError:
                pass
        waited = time.monotonic() - t0
        s.close()
        assert closed and waited < 5, waited
        assert v.get().status == 200
    finally:
        _, err = v.stop()
    assert "Traceback" not in err, err


def test_a_stop_while_a_handler_thread_starts_gives_its_slot_back_once_and_goes_on(monkeypatch):
    """A stop (here KeyboardInterrupt) can land in ``Thread.start()`` while it waits for a handler
    thread that has already answered and given its slot back. The stop must reach the server loop
    (not turn into "Semaphore released too many times", which let the viewer keep serving), and
    every slot must be free afterwards."""
    import threading

    srv = server.make_server({"/x": b"x"}, port=0)
    real_start = threading.Thread.start

    def start_then_stop(self):
        real_start(self)
        self.join(10)  # the handler ran and gave its slot back
        raise KeyboardInterrupt

    b = _connect(srv.server_port)
    a, address = srv.get_request()
    try:
        b.sendall(f"GET /x HTTP/1.0\r\nHost: 127.0.0.1:{srv.server_port}\r\n\r\n".encode())
        monkeypatch.setattr(threading.Thread, "start", start_then_stop)
        with pytest.raises(KeyboardInterrupt):
            srv.process_request(a, address)
        monkeypatch.undo()
        assert b.recv(1024).startswith(b"HTTP/1.0 200")
        for _ in range(srv.max_connections):  # every slot is free, and no more than those
            assert srv.slots.acquire(blocking=False)
        assert not srv.slots.acquire(blocking=False)
        assert not srv._slot_of
    finally:
        a.close()
        b.close()
        srv.server_close()
