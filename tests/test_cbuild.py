"""camio.cbuild.build_shared: the cache key covers the local headers a source includes."""

from __future__ import annotations

import ctypes

import pytest

from camio.cbuild import build_shared, find_compiler

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
    from splat_train import _cpu_build

    assert [h.name for h in _cpu_build._HEADERS] == ["_cpu_vec8d.h"]
