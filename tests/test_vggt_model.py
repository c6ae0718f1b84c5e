"""Parity of our VGGT implementation with the official one, on tiny reference fixtures.

Fixture sets: tests/data/vggt/<set>/ (committed copy of the official fixture set
``shared``) and, where this project's machine data is present (tests/_machine_data.py), every
official fixture set (a holdout set with other
sizes, depths and layer indices is picked up automatically if present).

Tolerances (fixtures README section 6): the float64 run reproduces the reference's float32
steps (mean/std constants, DINO pos-embed resize, RoPE tables, DPT embedding, unprojection
cast), so it must agree to rtol = atol = 1e-9 (measured round-off ~1e-13 abs); the float32
run agrees with the reference's float32 output to rtol = atol = 1e-4.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from vggt_init.geometry import pose_encoding_to_extri_intri, unproject_depth
from vggt_init.model import VGGT, VGGTConfig
from vggt_init.model.heads import activation
from _machine_data import VGGT_FIXTURES

safetensors_torch = pytest.importorskip("safetensors.torch")

DATA = Path(__file__).parent / "data" / "vggt"


def _sets() -> list:
    out = [pytest.param(p, id=f"repo-{p.name}") for p in sorted(DATA.iterdir())
           if (p / "weights.safetensors").is_file()]
    if VGGT_FIXTURES.is_dir():
        out += [pytest.param(p, id=f"shared-{p.name}", marks=pytest.mark.shared_data)
                for p in sorted(VGGT_FIXTURES.iterdir())
                if (p / "weights.safetensors").is_file() and not (DATA / p.name).exists()]
    return out


FIXTURE_SETS = _sets()


def _model(d: Path, dtype: torch.dtype, heads=("camera", "depth", "point")) -> VGGT:
    cfg = VGGTConfig.from_fixture_config(json.loads((d / "config.json").read_text()))
    model = VGGT(cfg, heads=heads)
    sd = safetensors_torch.load_file(str(d / "weights.safetensors"))
    sd = {k: v for k, v in sd.items() if k.split(".")[0] in {"aggregator"} | {f"{h}_head" for h in heads}}
    model.load_state_dict(sd, strict=True)
    return model.to(dtype).eval()


def _run_all(d: Path, dtype: torch.dtype) -> dict[str, torch.Tensor]:
    """Every tensor of expected*.safetensors computed by our code."""
    torch.manual_seed(0)
    model = _model(d, dtype)
    inputs = safetensors_torch.load_file(str(d / "inputs.safetensors"))
    x = inputs["images"].to(dtype)[None]
    H, W = x.shape[-2:]
    res: dict[str, torch.Tensor] = {}
    dbg: dict = {}
    with torch.inference_mode():
        out = model(x, debug=dbg)
        tokens = model.aggregator(x, keep=None)
        outb = model(inputs["images_batched"].to(dtype))
    for k in ("pose_enc", "depth", "depth_conf", "world_points", "world_points_conf"):
        res[k] = out[k]
    for i, p in enumerate(out["pose_enc_list"]):
        res[f"pose_enc_list.{i}"] = p
    for i, t in tokens.items():
        res[f"aggregator.tokens.{i}"] = t
    for k, v in dbg.items():
        res[f"debug.{k}"] = v
    extr, intr = pose_encoding_to_extri_intri(out["pose_enc"], (H, W))
    res["extrinsics"], res["intrinsics"] = extr, intr
    res["world_points_from_depth"] = torch.from_numpy(
        unproject_depth(out["depth"][0].numpy(), extr[0].numpy(), intr[0].numpy()))
    res["batched.pose_enc"], res["batched.depth"] = outb["pose_enc"], outb["depth"]
    return res


@pytest.mark.parametrize("fixture_dir", FIXTURE_SETS)
def test_float64_parity(fixture_dir):
    expected = safetensors_torch.load_file(str(fixture_dir / "expected.safetensors"))
    ours = _run_all(fixture_dir, torch.float64)
    assert set(expected) <= set(ours), f"not computed: {sorted(set(expected) - set(ours))}"
    for key, exp in expected.items():
        torch.testing.assert_close(ours[key].double(), exp.double(), rtol=1e-9, atol=1e-9, msg=lambda m: f"{key}: {m}")


@pytest.mark.parametrize("fixture_dir", FIXTURE_SETS)
def test_float32_parity(fixture_dir):
    expected = safetensors_torch.load_file(str(fixture_dir / "expected_fp32.safetensors"))
    ours = _run_all(fixture_dir, torch.float32)
    for key, exp in expected.items():
        assert ours[key].dtype in (torch.float32, torch.float64)
        torch.testing.assert_close(ours[key].double(), exp.double(), rtol=1e-4, atol=1e-4, msg=lambda m: f"{key}: {m}")


@pytest.mark.parametrize("fixture_dir", FIXTURE_SETS[:1])
def test_heads_subset_and_chunking_give_same_numbers(fixture_dir):
    """Building only the point head, and chunking the DPT over single frames, changes nothing."""
    inputs = safetensors_torch.load_file(str(fixture_dir / "inputs.safetensors"))
    x = inputs["images_batched"].double()
    full = _model(fixture_dir, torch.float64)
    only_point = _model(fixture_dir, torch.float64, heads=("camera", "point"))
    assert only_point.depth_head is None
    with torch.inference_mode():
        a = full(x)
        b = only_point(x, frames_chunk_size=1)
    assert set(b) == {"pose_enc", "pose_enc_list", "world_points", "world_points_conf"}
    torch.testing.assert_close(a["world_points"], b["world_points"], rtol=0, atol=1e-12)
    torch.testing.assert_close(a["pose_enc"], b["pose_enc"], rtol=0, atol=0)
    # only the layers the heads read are kept
    cfg = full.config
    assert only_point.layers_needed == sorted({i % cfg.aggregator.depth for i in cfg.point_head.intermediate_layer_idx}
                                              | {cfg.camera_head.token_layer % cfg.aggregator.depth})


@pytest.mark.parametrize("fixture_dir", FIXTURE_SETS[:1])
def test_single_frame_and_batch_slot_rule(fixture_dir):
    """S = 1 works; scene 0 of a batch equals the unbatched run (each scene's own slot 0)."""
    inputs = safetensors_torch.load_file(str(fixture_dir / "inputs.safetensors"))
    model = _model(fixture_dir, torch.float64)
    with torch.inference_mode():
        one = model(inputs["images"][:1].double())
        batched = model(inputs["images_batched"].double())
        scene1 = model(inputs["images_batched"][1].double())
    assert one["depth"].shape[:2] == (1, 1)
    assert torch.isfinite(one["world_points"]).all()
    torch.testing.assert_close(batched["pose_enc"][1:2], scene1["pose_enc"], rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("fixture_dir", FIXTURE_SETS[:1])
def test_bf16_trunk_close_to_fp32(fixture_dir):
    """bf16 autocast on the trunk, heads in fp32: within 1e-2 relative (L2) of the fp32 run
    (measured ~1e-3). Storing the trunk weights in bf16 gives bit-identical numbers."""
    inputs = safetensors_torch.load_file(str(fixture_dir / "inputs.safetensors"))
    model = _model(fixture_dir, torch.float32)
    with torch.inference_mode():
        ref = model(inputs["images"])
        low = model(inputs["images"], trunk_dtype=torch.bfloat16)
        model.cast_trunk_weights(torch.bfloat16)
        cast = model(inputs["images"])
    assert model.aggregator.frame_blocks[0].attn.qkv.weight.dtype == torch.bfloat16
    assert model.point_head.norm.weight.dtype == torch.float32
    for k in ("pose_enc", "depth", "depth_conf", "world_points", "world_points_conf"):
        assert low[k].dtype == torch.float32
        rel = (low[k] - ref[k]).norm() / ref[k].norm()
        assert rel < 1e-2, f"{k}: relative difference {rel:.3g}"
        assert torch.equal(cast[k], low[k]), k


def test_activation_names():
    x = torch.tensor([-1.0, 0.0, 2.0], dtype=torch.float64)
    torch.testing.assert_close(activation("inv_log")(x), torch.sign(x) * (torch.exp(x.abs()) - 1))
    torch.testing.assert_close(activation("expp1")(x), 1 + torch.exp(x))
    with pytest.raises(ValueError, match="unknown activation"):
        activation("softplus_typo")


def test_bad_image_size_is_rejected():
    cfg = VGGTConfig.from_fixture_config(json.loads((DATA / "shared" / "config.json").read_text()))
    model = VGGT(cfg, heads=("camera",))
    with pytest.raises(ValueError, match="multiple of the 14"):
        model(torch.zeros(1, 3, 20, 28))


def test_holdout_shaped_architecture_counts_and_shapes():
    """Nothing is tied to the shared set's sizes: the holdout set's published architecture
    (C=40, depth 6, layers [1,2,4,5], DINO grid 4, input 28x70, S=4) gives the README's
    433 tensors / 832,912 parameters and its debug shapes."""
    cfg = json.loads((DATA / "shared" / "config.json").read_text())
    cfg["aggregator"].update(embed_dim=40, depth=6, num_heads=2)
    cfg["dino"].update(embed_dim=40, depth=2, num_heads=5, img_size=56, pos_embed_grid=4)
    cfg["camera_head"].update(dim_in=80, trunk_depth=3, num_heads=4, pose_branch_hidden=40)
    for k in ("depth_head", "point_head"):
        cfg[k].update(dim_in=80, features=24, out_channels=[16, 24, 32, 40], intermediate_layer_idx=[1, 2, 4, 5])
    model = VGGT(VGGTConfig.from_fixture_config(cfg)).eval()
    sd = model.state_dict()
    assert len(sd) == 433 and sum(v.numel() for v in sd.values()) == 832_912
    dbg: dict = {}
    with torch.inference_mode():
        out = model(torch.rand(4, 3, 28, 70), debug=dbg)
    assert out["depth"].shape == (1, 4, 28, 70, 1) and out["world_points"].shape == (1, 4, 28, 70, 3)
    assert dbg["dino.pos_embed"].shape == (1, 11, 40) and dbg["depth_head.fused"].shape == (4, 12, 16, 40)
    assert model.layers_needed == [1, 2, 4, 5]


def _meshgrid_embedding(hh: int, ww: int, channels: int, aspect: float, omega_0: float = 100.0) -> torch.Tensor:
    """The DPT embedding written as the reference builds it: a full [hh*ww] grid, float64 sin/cos."""
    diag = (aspect ** 2 + 1.0) ** 0.5
    sx, sy = aspect / diag, 1.0 / diag
    xs = torch.linspace(-sx * (ww - 1) / ww, sx * (ww - 1) / ww, steps=ww, dtype=torch.float64)
    ys = torch.linspace(-sy * (hh - 1) / hh, sy * (hh - 1) / hh, steps=hh, dtype=torch.float64)
    uu, vv = torch.meshgrid(xs, ys, indexing="xy")

    def sincos(pos, dim):
        omega = 1.0 / omega_0 ** (torch.arange(dim // 2, dtype=torch.float64) / (dim / 2.0))
        ang = pos.reshape(-1)[:, None] * omega[None, :]
        return torch.cat((torch.sin(ang), torch.cos(ang)), dim=1)

    emb = torch.cat((sincos(uu, channels // 2), sincos(vv, channels // 2)), dim=-1)
    return emb.float().reshape(hh, ww, channels).permute(2, 0, 1)


@pytest.mark.parametrize("hh,ww,channels,aspect", [(37, 37, 256, 1.0), (28, 37, 64, 518 / 392), (5, 3, 8, 0.6)])
def test_dpt_embedding_separable_form_is_exact(hh, ww, channels, aspect):
    """The two factors the heads add as broadcasts equal the reference's materialised
    [C, h, w] embedding bit for bit."""
    from vggt_init.model.heads import dpt_position_embedding

    ref = _meshgrid_embedding(hh, ww, channels, aspect)
    ex, ey = dpt_position_embedding(hh, ww, channels, aspect, torch.float64, torch.device("cpu"))
    assert ex.shape == (channels // 2, ww) and ey.shape == (channels // 2, hh) and ex.dtype == torch.float32
    full = torch.cat((ex[:, None, :].expand(-1, hh, -1), ey[:, :, None].expand(-1, -1, ww)), dim=0)
    assert torch.equal(full, ref)
    with pytest.raises(ValueError, match="divisible by 4"):
        dpt_position_embedding(4, 4, 6, 1.0, torch.float64, torch.device("cpu"))


@pytest.mark.parametrize("fixture_dir", FIXTURE_SETS[:1])
def test_dpt_heads_same_with_and_without_autograd(fixture_dir):
    """The DPT heads overwrite their own temporaries in place; with autograd recording, backward
    must still run (no tensor a backward needs is overwritten) and the numbers stay the same."""
    inputs = safetensors_torch.load_file(str(fixture_dir / "inputs.safetensors"))
    x = inputs["images"].double()[None]
    model = _model(fixture_dir, torch.float64, heads=("depth", "point"))
    with torch.no_grad():
        tokens = model.aggregator(x, keep=model.layers_needed)
        ref_depth = model.depth_head(tokens, x.shape[-2:], model.aggregator.patch_start_idx)
        ref_point = model.point_head(tokens, x.shape[-2:], model.aggregator.patch_start_idx)
    tokens = {k: v.clone().requires_grad_(True) for k, v in tokens.items()}
    depth, conf = model.depth_head(tokens, x.shape[-2:], model.aggregator.patch_start_idx)
    point, _ = model.point_head(tokens, x.shape[-2:], model.aggregator.patch_start_idx)
    torch.testing.assert_close(depth, ref_depth[0], rtol=0, atol=1e-12)
    torch.testing.assert_close(conf, ref_depth[1], rtol=0, atol=1e-12)
    torch.testing.assert_close(point, ref_point[0], rtol=0, atol=1e-12)
    (depth.sum() + point.sum()).backward()
    grads = [t.grad for t in tokens.values() if t.grad is not None]
    assert grads and all(torch.isfinite(g).all() for g in grads)
