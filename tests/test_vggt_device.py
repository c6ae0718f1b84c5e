"""vggt_init picks its device and dtype: ``auto`` = CUDA when available (bf16 autocast when the
GPU supports it), else CPU in fp32. Decisions only, with torch.cuda's answers monkeypatched."""

from __future__ import annotations

import pytest
import torch

from vggt_init.__main__ import build_parser
from vggt_init.run import RunOptions, resolve_device, resolve_dtype


def test_auto_is_cpu_without_cuda(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert resolve_device("auto") == torch.device("cpu")
    assert resolve_dtype("auto", torch.device("cpu")) == "fp32"
    with pytest.raises(ValueError, match="no CUDA device"):
        resolve_device("cuda:0")


def test_auto_is_cuda_when_available(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert resolve_device("auto") == torch.device("cuda")
    assert resolve_device("cuda:1") == torch.device("cuda:1")
    assert resolve_device("cpu") == torch.device("cpu")


@pytest.mark.parametrize("bf16_ok,want", [(True, "bf16"), (False, "fp32")])
def test_auto_dtype_on_cuda_follows_bf16_support(monkeypatch, bf16_ok, want):
    monkeypatch.setattr(torch.cuda, "is_bf16_supported", lambda *a, **k: bf16_ok)
    assert resolve_dtype("auto", torch.device("cuda")) == want
    assert resolve_dtype("fp32", torch.device("cuda")) == "fp32"  # explicit choices are kept
    assert resolve_dtype("bf16", torch.device("cpu")) == "bf16"


def test_bad_names_raise():
    with pytest.raises(ValueError, match="dtype must be one of"):
        resolve_dtype("fp16", torch.device("cpu"))
    with pytest.raises(ValueError, match="device must be"):
        resolve_device("gpu")


def test_cli_defaults_are_run_options_defaults():
    args = build_parser().parse_args(["--images", "i", "--out", "o"])
    assert args.device is None and args.dtype is None  # RunOptions supplies them
    assert RunOptions(images="i", out="o").device == "auto" and RunOptions(images="i", out="o").dtype == "auto"
    args = build_parser().parse_args(["--images", "i", "--out", "o", "--device", "auto", "--dtype", "auto"])
    assert args.device == "auto" and args.dtype == "auto"
