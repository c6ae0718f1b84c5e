"""splat_train.render.cpu.optim: the trainer's Adam step on the kernel's threads, against torch.optim.Adam."""

import pytest
import torch

from splat_train.render.cpu import optim as cpu_optim
from splat_train.render.cpu.build import kernel_threads, set_kernel_threads

pytestmark = pytest.mark.skipif(not cpu_optim.available(), reason="no C++ compiler for the CPU kernels")

# the trainer's parameter groups: one tensor each, own rates, sizes across chunk boundaries
SHAPES = {"means": (5003, 3), "sh_dc": (5003, 3), "sh_rest": (5003, 15, 3), "opacity": (5003, 1),
          "scales": (5003, 3), "quats": (5003, 4)}
LRS = {"means": 1.6e-4, "sh_dc": 2.5e-3, "sh_rest": 1.25e-4, "opacity": 5e-2, "scales": 5e-3, "quats": 1e-3}


def _setup(dtype, fused, seed=0):
    g = torch.Generator().manual_seed(seed)
    params = {k: torch.nn.Parameter(torch.randn(*s, generator=g, dtype=torch.float64).to(dtype)) for k, s in SHAPES.items()}
    opt = torch.optim.Adam([{"params": [params[k]], "lr": LRS[k], "name": k} for k in SHAPES], lr=0.0, eps=1e-15,
                           fused=fused)
    return params, opt


def _grads(step, dtype):
    g = torch.Generator().manual_seed(100 + step)
    out = {k: torch.randn(*s, generator=g, dtype=torch.float64) * 10.0 ** (step % 3 - 2) for k, s in SHAPES.items()}
    out["sh_rest"][::7] = 0.0  # Gaussians out of view: zero gradient, moments still decay
    return {k: v.to(dtype) for k, v in out.items()}


@pytest.mark.parametrize("threads", [1, 2, 3])
def test_adam_step_matches_torch_adam(threads):
    """Ten steps with changing rates: parameters and both moments within float32 rounding of a
    float64 torch.optim.Adam run on the same gradients (rtol 1e-5, atol 1e-6 on values of order
    1); the step counter advances as torch's."""
    old = kernel_threads()
    set_kernel_threads(threads)
    try:
        ours, opt = _setup(torch.float32, True)
        ref, ref_opt = _setup(torch.float64, False)
        for step in range(10):
            grads = _grads(step, torch.float32)
            for k in SHAPES:
                ours[k].grad = grads[k].clone()
                ref[k].grad = grads[k].to(torch.float64)
            if step == 5:  # the trainer's position rate changes every step
                opt.param_groups[0]["lr"] *= 0.5
                ref_opt.param_groups[0]["lr"] *= 0.5
            ran = cpu_optim.adam_step(opt)
            assert ran == (step > 0)  # the first step creates torch's state through opt.step()
            ref_opt.step()
        for k in SHAPES:
            st, rst = opt.state[ours[k]], ref_opt.state[ref[k]]
            assert float(st["step"]) == float(rst["step"]) == 10.0
            torch.testing.assert_close(ours[k].detach().double(), ref[k].detach(), rtol=1e-5, atol=1e-6)
            # moments of order 1 (gradients up to ~3): float32 rounding over ten steps
            torch.testing.assert_close(st["exp_avg"].double(), rst["exp_avg"], rtol=1e-5, atol=1e-6)
            torch.testing.assert_close(st["exp_avg_sq"].double(), rst["exp_avg_sq"], rtol=1e-5, atol=1e-6)
    finally:
        set_kernel_threads(old)


def test_adam_step_is_deterministic_across_threads():
    """Every element is updated on its own: the same bits for any thread count."""
    old = kernel_threads()
    results = []
    try:
        for threads in (1, 2, 3):
            set_kernel_threads(threads)
            params, opt = _setup(torch.float32, True)
            for step in range(3):
                for k, v in _grads(step, torch.float32).items():
                    params[k].grad = v
                cpu_optim.adam_step(opt)
            results.append(torch.cat([p.detach().reshape(-1) for p in params.values()]))
    finally:
        set_kernel_threads(old)
    assert torch.equal(results[0], results[1]) and torch.equal(results[0], results[2])


def test_adam_step_falls_back_to_torch():
    """A missing gradient, float64 parameters, weight decay or groups with different betas:
    optimizer.step() runs (same result as calling it directly)."""
    for case in ("no_grad", "float64", "weight_decay", "betas"):
        dtype = torch.float64 if case == "float64" else torch.float32
        a, opt_a = _setup(dtype, True)
        b, opt_b = _setup(dtype, True)
        for opt in (opt_a, opt_b):
            if case == "weight_decay":
                for group in opt.param_groups:
                    group["weight_decay"] = 0.01
            if case == "betas":
                opt.param_groups[2]["betas"] = (0.8, 0.99)
        for step in range(2):
            for params in (a, b):
                for k, v in _grads(step, dtype).items():
                    params[k].grad = None if (case == "no_grad" and k == "quats") else v.clone()
            assert cpu_optim.adam_step(opt_a) is False
            opt_b.step()
        for k in SHAPES:
            assert torch.equal(a[k].detach(), b[k].detach()), (case, k)


def test_fused_adam_step_matches_the_optimizers_own_step():
    """The direct fused-kernel step (the trainer's path on a GPU) gives exactly
    ``optimizer.step()``'s parameters and state, over steps with changing rates (checked on the
    CPU, where torch's fused Adam also runs)."""
    from splat_train.gaussians import fused_adam_step

    g = torch.Generator().manual_seed(3)
    shapes = [(7, 3), (7,), (7, 15, 3)]
    ours = [torch.nn.Parameter(torch.randn(s, generator=g)) for s in shapes]
    ref = [torch.nn.Parameter(p.detach().clone()) for p in ours]
    mk = lambda ps: torch.optim.Adam([{"params": [p], "lr": 0.01 * (i + 1)} for i, p in enumerate(ps)],  # noqa: E731
                                     eps=1e-15, fused=True)
    opt_a, opt_b = mk(ours), mk(ref)
    assert not fused_adam_step(opt_a, devices=("cpu",))  # no state before the first step: not applicable
    for step in range(5):
        grads = [torch.randn(s, generator=g) for s in shapes]
        for p, q, gr in zip(ours, ref, grads):
            p.grad, q.grad = gr.clone(), gr.clone()
        for ga, gb in zip(opt_a.param_groups, opt_b.param_groups):
            ga["lr"] = gb["lr"] = ga["lr"] * 0.9
        if step == 0:
            opt_a.step()
        else:
            assert fused_adam_step(opt_a, devices=("cpu",))
        opt_b.step()
    for p, q in zip(ours, ref):
        assert torch.equal(p, q)
        for k in ("step", "exp_avg", "exp_avg_sq"):
            assert torch.equal(opt_a.state[p][k], opt_b.state[q][k])
    assert not fused_adam_step(opt_a)  # CPU parameters: the trainer's CPU path is the C++ kernel
