"""Which rasterizer backend runs: ``resolve_backend`` decisions, the CUDA-without-gsplat warning
and the config check. Decisions only (no GPU here): the device is a ``torch.device`` and the
availability checks are monkeypatched."""

from __future__ import annotations

import importlib
import logging

import pytest
import torch

from splat_train.render import _gsplat_backend
from splat_train.render.cpu import raster as cpu_raster
from splat_train.config import TrainConfig
from splat_train.render.rasterize import BACKENDS, resolve_backend

rasterize_mod = importlib.import_module("splat_train.render.rasterize")  # the module, not splat_train.rasterize


@pytest.fixture
def fresh_warning(monkeypatch):
    monkeypatch.setattr(rasterize_mod, "_warned_cuda_fallback", False)


def test_auto_on_cpu_is_the_kernel_or_torch():
    assert resolve_backend("auto", torch.device("cpu")) == ("cpu" if cpu_raster.available() else "torch")
    assert resolve_backend("auto", "cpu") == resolve_backend("auto", torch.device("cpu"))


@pytest.mark.parametrize("name", [b for b in BACKENDS if b != "auto"])
def test_explicit_backend_is_kept(name):
    assert resolve_backend(name, "cpu") == name
    if name == "cpu":  # C++ kernels on CPU memory: refused before any pointer reaches them
        with pytest.raises(ValueError, match="CPU tensors only"):
            resolve_backend(name, "cuda")
    else:
        assert resolve_backend(name, "cuda") == name


def test_unknown_backend_raises():
    with pytest.raises(ValueError, match="backend must be one of"):
        resolve_backend("cuda", "cpu")
    with pytest.raises(ValueError, match="rasterizer must be one of"):
        TrainConfig(rasterizer="gsplat-cuda")


def test_auto_on_cuda_with_gsplat(monkeypatch, fresh_warning, caplog):
    monkeypatch.setattr(_gsplat_backend, "available", lambda: True)
    with caplog.at_level(logging.WARNING, logger="splat_train.render.rasterize"):
        assert resolve_backend("auto", torch.device("cuda")) == "gsplat"
    assert not caplog.records


def test_auto_on_cuda_without_gsplat_falls_back_with_one_warning(monkeypatch, fresh_warning, caplog):
    monkeypatch.setattr(_gsplat_backend, "available", lambda: False)
    with caplog.at_level(logging.WARNING, logger="splat_train.render.rasterize"):
        assert resolve_backend("auto", torch.device("cuda")) == "torch"
        assert resolve_backend("auto", torch.device("cuda:0")) == "torch"
    warnings = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1
    assert "gsplat is not installed" in warnings[0].getMessage()
    assert ".[gpu]" in warnings[0].getMessage()
