"""Uniform draws on the training device from the trainer's CPU generator, without a device sync.

Every random draw of training comes from one CPU ``torch.Generator`` (the trainer's, saved in
each checkpoint). Drawing on the CPU and copying the result to a GPU makes the copy wait for
the device's queue (a host-to-device copy from pageable memory is synchronous), once per
iteration per draw. :func:`uniform` keeps the CPU draw on the CPU and, on any other device,
takes one 63-bit seed from the CPU generator and draws on the device from a device generator
seeded with it: the stream is still decided by the CPU generator alone (a resumed run draws the
same numbers), and nothing waits.
"""

from __future__ import annotations

import torch

__all__ = ["uniform"]

_DEVICE_GENERATORS: dict[torch.device, torch.Generator] = {}


def _device_generator(device: torch.device) -> torch.Generator:
    gen = _DEVICE_GENERATORS.get(device)
    if gen is None:
        gen = _DEVICE_GENERATORS[device] = torch.Generator(device=device)
    return gen


def uniform(shape: int | tuple[int, ...], generator: torch.Generator, device: torch.device | str,
            dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """U[0, 1) samples of ``shape`` on ``device``, decided by the CPU ``generator``.

    Args:
        shape: the result's shape.
        generator: a CPU generator (advanced by one draw of ``shape`` on the CPU, or by one
            int64 seed elsewhere).
        device: where the result lives.
        dtype: the result's dtype.

    Returns:
        ``shape`` tensor on ``device``: on the CPU exactly ``torch.rand(shape, generator)``;
        on another device the draw of a device generator seeded from ``generator``.
    """
    device = torch.device(device)
    if device.type == "cpu":
        return torch.rand(shape, generator=generator, dtype=dtype)
    seed = int(torch.randint(0, 2**63 - 1, (1,), generator=generator))
    gen = _device_generator(device)
    gen.manual_seed(seed)
    return torch.rand(shape, generator=gen, dtype=dtype, device=device)
