"""runtime.cbuild.build_shared: the cache key covers the local headers a source includes."""

from __future__ import annotations

import ctypes

import pytest

from runtime.cbuild import build_shared, find_compiler

CXX = find_compiler()
FLAGS = ["-O1", "-std=c++17", "-fPIC", "-shared"]


@pytest.mark.skipif(CXX is None, reason="no C++ compiler")
def test_editing_an_included_header_rebuilds(tmp_path):
    src = tmp_path / "k.cpp"
    hdr = tmp_path / "k.h"
    src.write_text('#include "k.h"\nextern "C" int value() { return VALUE; }\n')
    hdr.write_text("#define VALUE 1\n")
    first = build_shared(src, FLAGS, tmp_path / "cache", "k", CXX, headers=(hdr,))
    assert build_shared(src, FLAGS, tmp_path / "cache", "k", CXX, headers=(hdr,)) == first  # cached
    hdr.write_text("#define VALUE 2\n")
    second = build_shared(src, FLAGS, tmp_path / "cache", "k", CXX, headers=(hdr,))
    assert second != first
    assert ctypes.CDLL(str(first)).value() == 1 and ctypes.CDLL(str(second)).value() == 2


def test_kernels_name_the_shared_vector_header():
    from splat_train.render.cpu import build as cpu_build

    assert [h.name for h in cpu_build._HEADERS] == ["vec8d.h"]


def test_wheel_carries_the_kernel_sources():
    """The kernels compile from their sources at first use, so pyproject.toml's package-data
    must ship every .cpp / .h beside the loaders (setuptools adds no such file by itself)."""
    import fnmatch
    from pathlib import Path

    tomllib = pytest.importorskip("tomllib")
    root = Path(__file__).resolve().parents[1]
    data = tomllib.loads((root / "pyproject.toml").read_text())["tool"]["setuptools"]["package-data"]
    for src in [*root.glob("splat_train/**/*.cpp"), *root.glob("splat_train/**/*.h"),
                *root.glob("vggt_init/**/*.cpp")]:
        package = ".".join(src.parent.relative_to(root).parts)
        assert any(fnmatch.fnmatch(src.name, pat) for pat in data.get(package, [])), (package, src.name)
