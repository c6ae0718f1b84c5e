"""Checkpoints: resolution order, safe loading, clear offline error, strict key/shape check."""

from __future__ import annotations

import functools
import json
import pickle
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file, save_file

from vggt_init import checkpoint as ck
from vggt_init.model import VGGTConfig

DATA = Path(__file__).parent / "data" / "vggt"
FIX = DATA / "shared"


def _manifest() -> dict[str, tuple[int, ...]]:
    rows = (DATA / "vggt1b_state_dict_manifest.tsv").read_text().splitlines()
    assert rows[0].split("\t") == ["name", "shape", "dtype"]
    out = {}
    for line in rows[1:]:
        name, shape, dtype = line.split("\t")
        assert dtype == "float32"
        out[name] = tuple(json.loads(shape))
    return out


def test_default_model_matches_manifest_on_meta():
    manifest = _manifest()
    assert len(manifest) == 1797
    ours = ck.expected_shapes(VGGTConfig())
    non_track = {k: v for k, v in manifest.items() if not k.startswith("track_head.")}
    assert set(ours) == set(non_track)
    assert ours == non_track
    n = sum(int(torch.Size(s).numel()) for s in ours.values())
    assert n == 1_190_596_120


def test_check_state_dict_skips_only_track_head():
    manifest = _manifest()
    cfg = VGGTConfig()
    skipped = ck.check_state_dict(manifest, cfg)
    assert len(skipped) == 394 and all(k.startswith("track_head.") for k in skipped)

    broken = dict(manifest)
    del broken["depth_head.scratch.output_conv2.2.bias"]
    with pytest.raises(ck.StateDictMismatchError, match="1 missing: depth_head.scratch.output_conv2.2.bias"):
        ck.check_state_dict(broken, cfg)
    broken = dict(manifest, **{"point_head.extra.weight": (3,)})
    with pytest.raises(ck.StateDictMismatchError, match="unexpected: point_head.extra.weight"):
        ck.check_state_dict(broken, cfg)
    broken = dict(manifest, **{"aggregator.camera_token": (1, 2, 1, 512)})
    with pytest.raises(ck.StateDictMismatchError, match="wrong shape: aggregator.camera_token"):
        ck.check_state_dict(broken, cfg)


# ------------------------------------------------------------------------ resolution order
def _touch(p: Path) -> Path:
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_bytes(b"x")
    return p


def _fake_hf_cache(root: Path, filename: str) -> Path:
    repo = root / "models--facebook--VGGT-1B"
    (repo / "refs").mkdir(parents=True)
    (repo / "refs" / "main").write_text("abc123")
    return _touch(repo / "snapshots" / "abc123" / filename)


def test_resolution_order(tmp_path):
    explicit = _touch(tmp_path / "explicit.pt")
    from_env = _touch(tmp_path / "env.safetensors")
    cached = _fake_hf_cache(tmp_path / "hub", "model.pt")
    lookup = functools.partial(ck._hf_cache_lookup, cache_dir=tmp_path / "hub")
    downloads = []

    def fake_download(repo_id, names):
        downloads.append(repo_id)
        return _touch(tmp_path / "downloaded" / "model.safetensors")

    env = {ck.ENV_VAR: str(from_env)}
    kw = dict(cache_lookup=lookup, download=fake_download)
    assert ck.resolve_checkpoint(explicit, env=env, **kw) == explicit
    assert ck.resolve_checkpoint(None, env=env, **kw) == from_env
    assert ck.resolve_checkpoint(None, env={}, **kw) == cached
    empty = functools.partial(ck._hf_cache_lookup, cache_dir=tmp_path / "empty_hub")
    assert ck.resolve_checkpoint(None, env={}, cache_lookup=empty, download=fake_download).name == "model.safetensors"
    assert downloads == ["facebook/VGGT-1B"]
    # offline: no download attempted, one clear error saying where to put the file
    with pytest.raises(ck.CheckpointNotFoundError) as err:
        ck.resolve_checkpoint(None, env={"HF_HUB_OFFLINE": "1"}, cache_lookup=empty, download=fake_download)
    assert downloads == ["facebook/VGGT-1B"]
    msg = str(err.value)
    for needle in ("--checkpoint", ck.ENV_VAR, "models--facebook--VGGT-1B", "model.pt", "huggingface-cli download"):
        assert needle in msg
    with pytest.raises(ck.CheckpointNotFoundError, match="does not exist"):
        ck.resolve_checkpoint(tmp_path / "nope.pt", env={}, **kw)
    with pytest.raises(ck.CheckpointNotFoundError, match=ck.ENV_VAR):
        ck.resolve_checkpoint(None, env={ck.ENV_VAR: str(tmp_path / "nope.pt")}, **kw)


def test_failed_download_gives_the_same_clear_error(tmp_path):
    empty = functools.partial(ck._hf_cache_lookup, cache_dir=tmp_path / "empty_hub")
    with pytest.raises(ck.CheckpointNotFoundError, match="no VGGT checkpoint found"):
        ck.resolve_checkpoint(None, env={}, cache_lookup=empty, download=lambda repo, names: None)


# ------------------------------------------------------------------------ safe loading
class _Evil:
    """Unpickling this would run code (create a marker file)."""

    def __init__(self, marker: str) -> None:
        self.marker = marker

    def __reduce__(self):
        return (Path.touch, (Path(self.marker),))


@pytest.mark.filterwarnings("ignore:Detected pickle protocol")
def test_malicious_pickle_is_refused(tmp_path):
    marker = tmp_path / "pwned"
    bad = tmp_path / "evil.pt"
    torch.save({"aggregator.camera_token": torch.zeros(1), "payload": _Evil(str(marker))}, bad)
    with pytest.raises(ck.CheckpointFormatError, match="refusing to load"):
        ck.read_state_dict(bad)
    assert not marker.exists()
    raw = tmp_path / "raw.pt"
    raw.write_bytes(pickle.dumps(_Evil(str(marker))))
    with pytest.raises(ck.CheckpointFormatError):
        ck.read_state_dict(raw)
    assert not marker.exists()
    # the payload is real: a plain unpickle would have run it
    pickle.loads(raw.read_bytes())
    assert marker.exists()


def test_read_formats(tmp_path):
    sd = {"a": torch.arange(3.0), "b": torch.ones(2, 2)}
    torch.save(sd, tmp_path / "m.pt")
    torch.save({"state_dict": sd}, tmp_path / "nested.pth")
    save_file(sd, str(tmp_path / "m.safetensors"))
    for name in ("m.pt", "nested.pth", "m.safetensors"):
        got = ck.read_state_dict(tmp_path / name)
        assert set(got) == {"a", "b"} and torch.equal(got["b"], sd["b"])
    assert set(ck.read_state_dict(tmp_path / "m.safetensors", keys=["a"])) == {"a"}
    (tmp_path / "m.npz").write_bytes(b"x")
    with pytest.raises(ck.CheckpointFormatError, match="unknown checkpoint format"):
        ck.read_state_dict(tmp_path / "m.npz")
    torch.save([torch.zeros(1)], tmp_path / "list.pt")
    with pytest.raises(ck.CheckpointFormatError, match="flat dict of tensors"):
        ck.read_state_dict(tmp_path / "list.pt")


def test_load_model_skips_track_head_and_checks_the_rest(tmp_path):
    cfg = VGGTConfig.from_fixture_config(json.loads((FIX / "config.json").read_text()))
    sd = load_file(str(FIX / "weights.safetensors"))
    with_track = dict(sd, **{"track_head.tracker.fmap_norm.weight": torch.ones(4)})
    torch.save(with_track, tmp_path / "model.pt")
    model = ck.load_model(cfg, tmp_path / "model.pt", heads=("camera", "point"))
    assert model.depth_head is None and model.point_head is not None
    assert not any(p.requires_grad for p in model.parameters())
    assert all(p.device.type == "cpu" for p in model.parameters())
    torch.testing.assert_close(model.state_dict()["point_head.norm.weight"], sd["point_head.norm.weight"])
    # a non-track key missing from the file is an error even for a head we do not build
    del with_track["depth_head.norm.bias"]
    save_file(with_track, str(tmp_path / "broken.safetensors"))
    with pytest.raises(ck.StateDictMismatchError, match="depth_head.norm.bias"):
        ck.load_model(cfg, tmp_path / "broken.safetensors", heads=("camera", "point"))


def test_unreachable_hub_says_it_will_not_download_and_never_that_it_is_downloading(monkeypatch, caplog):
    import logging

    from vggt_init import checkpoint

    monkeypatch.setattr(checkpoint, "hub_unreachable_reason", lambda *a, **k: "huggingface.co:443 cannot be reached")
    with caplog.at_level(logging.INFO, logger=checkpoint.__name__):
        assert checkpoint._hf_download("facebook/VGGT-1B", ["model.pt"]) is None
    text = caplog.text
    assert "not downloading facebook/VGGT-1B" in text
    assert "downloading facebook/VGGT-1B from" not in text


def test_finding_a_checkpoint_imports_no_torch():
    """The workflow asks whether VGGT can run at every Snakefile parse (each SLURM job parses
    it): finding the checkpoint must not pay torch's import."""
    code = ("import sys, vggt_init.checkpoint as c; c.skip_reason(env={'HF_HUB_OFFLINE': '1'}); "
            "print('torch' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         cwd=Path(__file__).resolve().parents[1])
    assert out.returncode == 0 and out.stdout.strip() == "False", out.stdout + out.stderr
