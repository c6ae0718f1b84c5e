"""Splits exactly as docs/reference.md section 4, manifests, split.json."""

from __future__ import annotations

import json

import numpy as np
import pytest

from camio.split import make_split, read_split, select_train, every8_split, write_split


def test_every8_rule_by_sorted_name():
    names = [f"img{i:03d}.png" for i in range(20)][::-1]  # given unsorted
    test, pool = every8_split(names)
    assert test == ["img000.png", "img008.png", "img016.png"]
    assert len(pool) == 17 and pool == sorted(pool) and not set(test) & set(pool)


def test_linspace_round_half_to_even():
    pool = list(range(13))
    # linspace(0, 12, 9) = 0, 1.5, 3, 4.5, 6, 7.5, 9, 10.5, 12; np.round halves to even
    assert select_train(pool, 9) == [0, 2, 3, 4, 6, 8, 9, 10, 12]
    assert select_train(pool, 3) == [0, 6, 12]
    assert select_train(pool, 1) == [0]
    for n in range(1, 14):
        expect = [pool[i] for i in np.round(np.linspace(0, 12, n)).astype(int)]
        assert select_train(pool, n) == expect


def test_fern_like_20_and_synthetic_24():
    s = make_split([f"image{i:03d}.png" for i in range(20)], (3, 6, 9, 12))
    assert s.test == ["image000.png", "image008.png", "image016.png"]
    assert s.train["3"] == ["image001.png", "image010.png", "image019.png"]
    s24 = make_split([f"{i:04d}.png" for i in range(24)], (3, 6, 9, 12))
    assert len(s24.test) == 3 and len(s24.train_pool) == 21 and len(s24.train["12"]) == 12
    for n in ("3", "6", "9", "12"):
        assert not set(s24.train[n]) & set(s24.test)
        assert len(set(s24.train[n])) == int(n)


def test_too_many_views_is_clear_error():
    with pytest.raises(ValueError, match="pool holds only 2"):
        make_split(["a", "b", "c"], (3,))
    with pytest.raises(ValueError, match=">= 1"):
        select_train(["a"], 0)
    with pytest.raises(ValueError, match="empty"):
        make_split([], (3,))


def test_manifest_overrides(tmp_path):
    names = [f"{i}.png" for i in range(10)]
    m = tmp_path / "m.json"
    m.write_text(json.dumps({"test": ["9.png", "0.png"], "train": ["1.png", "5.png", "7.png"]}))
    s = make_split(names, (3,), manifest=m)
    assert s.rule == "manifest" and s.test == ["0.png", "9.png"] and s.train == {"3": ["1.png", "5.png", "7.png"]}
    m.write_text(json.dumps({"test": ["0.png"], "train": {"2": ["1.png", "2.png"], "3": ["1.png", "2.png", "3.png"]}}))
    s = make_split(names, (2, 3), manifest=m)
    assert s.train["2"] == ["1.png", "2.png"]
    with pytest.raises(ValueError, match="n = \\['6'\\]"):
        make_split(names, (6,), manifest=m)
    m.write_text(json.dumps({"test": ["0.png"], "train": ["0.png", "1.png"]}))
    with pytest.raises(ValueError, match="both test and train"):
        make_split(names, (2,), manifest=m)
    m.write_text(json.dumps({"test": ["zz.png"], "train": ["1.png"]}))
    with pytest.raises(ValueError, match="not in the scene"):
        make_split(names, (1,), manifest=m)
    m.write_text("{not json")
    with pytest.raises(ValueError, match="cannot read split manifest"):
        make_split(names, (1,), manifest=m)


def test_write_read_split(tmp_path):
    s = make_split([f"{i}.png" for i in range(24)], (3, 6))
    p = write_split(tmp_path / "out" / "split.json", s)
    data = json.loads(p.read_text())
    assert set(data) == {"rule", "test", "train_pool", "train"}
    assert data["rule"] == "every8" and set(data["train"]) == {"3", "6"}
    assert read_split(p) == s
