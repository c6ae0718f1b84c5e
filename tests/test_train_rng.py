"""splat_train.rng.uniform: the trainer's draws (dropout masks, random backgrounds) come from its
CPU generator on every device; on the CPU exactly torch.rand's numbers."""

from __future__ import annotations

import torch

from splat_train.rng import uniform


def test_uniform_on_the_cpu_is_torch_rand_from_the_generator():
    a = uniform(1000, torch.Generator().manual_seed(5), "cpu")
    b = torch.rand(1000, generator=torch.Generator().manual_seed(5))
    assert torch.equal(a, b) and a.dtype == torch.float32


def test_uniform_follows_the_generator_state():
    """The same generator state gives the same draws (a resumed run's masks), and each draw
    advances it (successive masks differ)."""
    g = torch.Generator().manual_seed(7)
    state = g.get_state()
    first, second = uniform((4, 3), g, "cpu"), uniform((4, 3), g, "cpu")
    assert not torch.equal(first, second) and first.shape == (4, 3)
    g.set_state(state)
    assert torch.equal(uniform((4, 3), g, "cpu"), first)
    assert ((first >= 0) & (first < 1)).all()
