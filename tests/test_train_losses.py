"""splat_train.losses: SSIM exactly as 3DGS computes it, against a direct float64 sum."""

import numpy as np
import pytest
import torch

from splat_train.losses import gaussian_window, l1_loss, photometric_loss, psnr, ssim



pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py

def _ssim_direct(a: np.ndarray, b: np.ndarray, size: int = 11, sigma: float = 1.5) -> float:
    """Float64 SSIM by explicit window sums with zero padding ([H, W, C] images)."""
    x = np.arange(size) - size // 2
    g = np.exp(-(x ** 2) / (2 * sigma ** 2))
    g /= g.sum()
    w = np.outer(g, g)
    h, wd, c = a.shape
    r = size // 2
    pa = np.pad(a, ((r, r), (r, r), (0, 0)))
    pb = np.pad(b, ((r, r), (r, r), (0, 0)))
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    total = 0.0
    for i in range(h):
        for j in range(wd):
            wa = pa[i:i + size, j:j + size]
            wb = pb[i:i + size, j:j + size]
            mu1 = np.einsum("ij,ijc->c", w, wa)
            mu2 = np.einsum("ij,ijc->c", w, wb)
            s11 = np.einsum("ij,ijc->c", w, wa * wa) - mu1 ** 2
            s22 = np.einsum("ij,ijc->c", w, wb * wb) - mu2 ** 2
            s12 = np.einsum("ij,ijc->c", w, wa * wb) - mu1 * mu2
            m = ((2 * mu1 * mu2 + c1) * (2 * s12 + c2)) / ((mu1 ** 2 + mu2 ** 2 + c1) * (s11 + s22 + c2))
            total += m.sum()
    return total / (h * wd * c)


def test_window_is_normalised_gaussian():
    w = gaussian_window(11, 1.5, dtype=torch.float64)
    assert w.shape == (11, 11)
    assert float(w.sum()) == pytest.approx(1.0, abs=1e-12)
    assert float(w[5, 5]) == float(w.max())
    assert float(w[5, 6] / w[5, 5]) == pytest.approx(np.exp(-1 / (2 * 1.5 ** 2)), rel=1e-12)


def test_ssim_matches_direct_float64():
    rng = np.random.default_rng(0)
    a = rng.uniform(0, 1, (14, 17, 3))
    b = np.clip(a + rng.normal(0, 0.2, a.shape), 0, 1)
    want = _ssim_direct(a, b)
    got64 = ssim(torch.tensor(a), torch.tensor(b))
    assert float(got64) == pytest.approx(want, abs=1e-12)
    # float32 path: tolerance from single-precision cancellation in E[x^2] - mu^2.
    got32 = ssim(torch.tensor(a, dtype=torch.float32), torch.tensor(b, dtype=torch.float32))
    assert float(got32) == pytest.approx(want, abs=2e-5)


def test_ssim_layouts_and_reduction():
    rng = np.random.default_rng(1)
    a = torch.tensor(rng.uniform(0, 1, (2, 3, 12, 13)))
    b = torch.tensor(rng.uniform(0, 1, (2, 3, 12, 13)))
    per = ssim(a, b, reduction="none")
    assert per.shape == (2,)
    torch.testing.assert_close(ssim(a, b), per.mean())
    hwc = ssim(a[1].permute(1, 2, 0), b[1].permute(1, 2, 0))
    torch.testing.assert_close(hwc, per[1])
    with pytest.raises(ValueError, match="shape"):
        ssim(a[0, 0], b[0, 0])
    with pytest.raises(ValueError, match="differ"):
        ssim(a, b[:1])


def test_ssim_identical_is_one_and_gradient_finite():
    a = torch.rand(16, 20, 3, dtype=torch.float64, requires_grad=True)
    s = ssim(a, a.detach())
    assert float(s.detach()) == pytest.approx(1.0, abs=1e-12)
    b = torch.rand(16, 20, 3, dtype=torch.float64)
    ssim(a, b).backward()
    assert torch.isfinite(a.grad).all()


def test_photometric_loss_combination_and_psnr():
    rng = np.random.default_rng(2)
    a = torch.tensor(rng.uniform(0, 1, (10, 12, 3)))
    b = torch.tensor(rng.uniform(0, 1, (10, 12, 3)))
    loss, l1, s = photometric_loss(a, b, 0.2)
    assert float(l1) == pytest.approx(float(np.abs(a.numpy() - b.numpy()).mean()), abs=1e-12)
    assert float(loss) == pytest.approx(0.8 * float(l1) + 0.2 * (1 - float(s)), abs=1e-12)
    assert float(l1_loss(a, a)) == 0.0
    assert psnr(a, a) == float("inf")
    mse = float(((a - b) ** 2).mean())
    assert psnr(a, b) == pytest.approx(-10 * np.log10(mse), abs=1e-9)


@pytest.mark.parametrize("dtype, tol", [(torch.float64, 1e-12), (torch.float32, 2e-5)])
@pytest.mark.parametrize("shape", [(1, 3, 37, 53), (2, 3, 9, 12), (1, 1, 5, 30)])
def test_cpu_ssim_matches_reference(dtype, tol, shape):
    """The C++ SSIM of the training loss: value and gradient as the conv2d reference (float64
    to 1e-12, float32 to 2e-5 relative to the largest gradient entry), including images
    smaller than the 11 x 11 window in one direction (every column / row is a border)."""
    from splat_train.render.cpu import ssim as cpu_ssim

    if not cpu_ssim.available():
        pytest.skip("SSIM kernel did not build")
    g = torch.Generator().manual_seed(sum(shape))
    a = torch.rand(*shape, generator=g, dtype=dtype, requires_grad=True)
    b = (a.detach() + 0.2 * torch.randn(*shape, generator=g, dtype=dtype)).clamp(0, 1)
    ref = ssim(a, b)
    (g_ref,) = torch.autograd.grad(ref, a)
    got = cpu_ssim.ssim_cpu(a, b)
    (g_got,) = torch.autograd.grad(3.0 * got, a)
    torch.testing.assert_close(got, ref, rtol=tol, atol=tol)
    torch.testing.assert_close(g_got, 3.0 * g_ref, rtol=tol, atol=tol * g_ref.abs().max().item())


def test_training_loss_uses_the_same_ssim_as_the_reference():
    g = torch.Generator().manual_seed(7)
    render = torch.rand(20, 30, 3, generator=g, dtype=torch.float64, requires_grad=True)
    target = torch.rand(20, 30, 3, generator=g, dtype=torch.float64)
    loss, l1, s = photometric_loss(render, target, 0.2)
    torch.testing.assert_close(s, ssim(render, target), rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(loss, 0.8 * l1 + 0.2 * (1 - ssim(render, target)), rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("dtype, tol", [(torch.float64, 1e-12), (torch.float32, 2e-5)])
@pytest.mark.parametrize("shape", [(37, 53, 3), (9, 12, 3), (5, 30, 1), (150, 141, 3)])
def test_cpu_l1_ssim_matches_reference(dtype, tol, shape):
    """The fused [H, W, C] pass of the training loss: L1 and SSIM values, the gradient of the
    3DGS loss and of each term alone, as the torch reference (tolerances as above); equal
    pixels (sign 0, as torch's abs backward) and a non-contiguous render (the rasterizer's
    colour channels of a 4-channel buffer) included. 150 x 141: several bands of rows per
    channel (BAND_ROWS = 64) and every block size of the filters (4 vectors, 1 vector and
    scalar columns in both dtypes)."""
    from splat_train.render.cpu import ssim as cpu_ssim

    if not cpu_ssim.available():
        pytest.skip("SSIM kernel did not build")
    g = torch.Generator().manual_seed(sum(shape))
    buf = torch.rand(*shape[:2], shape[2] + 1, generator=g, dtype=dtype)
    b = (buf[..., :shape[2]] + 0.2 * torch.randn(*shape, generator=g, dtype=dtype)).clamp(0, 1)
    b[::3, ::2] = buf[::3, ::2, :shape[2]]  # ties: |a - b| = 0
    buf.requires_grad_(True)
    a = buf[..., :shape[2]]
    assert not a.is_contiguous()
    ref_l1, ref_s = l1_loss(a, b), ssim(a.permute(2, 0, 1)[None], b.permute(2, 0, 1)[None])
    l1, s = cpu_ssim.l1_ssim_cpu(a, b)
    torch.testing.assert_close(l1, ref_l1, rtol=tol, atol=tol)
    torch.testing.assert_close(s, ref_s, rtol=tol, atol=tol)
    # the loss's weights, then each term alone (the other output's cotangent is None)
    for got, ref in ((0.8 * l1 - 0.2 * s, 0.8 * ref_l1 - 0.2 * ref_s), (l1, ref_l1), (s, ref_s)):
        (g_ref,) = torch.autograd.grad(ref, buf, retain_graph=True)
        (g_got,) = torch.autograd.grad(got, buf, retain_graph=True)
        torch.testing.assert_close(g_got, g_ref, rtol=tol, atol=tol * g_ref.abs().max().item())


def test_cpu_l1_ssim_independent_of_thread_count(monkeypatch):
    """Values and gradient bit-identical on 1 and 2 kernel threads (work items write their own
    rows and partial sums, which are added in a fixed order)."""
    from splat_train.render.cpu import ssim as cpu_ssim
    from splat_train.render.cpu.build import set_kernel_threads

    if not cpu_ssim.available():
        pytest.skip("SSIM kernel did not build")
    monkeypatch.delenv("SPLAT_TRAIN_KERNEL_THREADS", raising=False)
    g = torch.Generator().manual_seed(5)
    a = torch.rand(150, 141, 3, generator=g, requires_grad=True)
    b = torch.rand(150, 141, 3, generator=g)
    out = []
    try:
        for n in (1, 2):
            set_kernel_threads(n)
            l1, s = cpu_ssim.l1_ssim_cpu(a, b)
            (ga,) = torch.autograd.grad(0.8 * l1 - 0.2 * s, a)
            out.append((l1.detach(), s.detach(), ga))
    finally:
        set_kernel_threads(None)
    for x, y in zip(*out):
        assert torch.equal(x, y)


def test_photometric_loss_fused_path_equals_the_two_terms():
    """photometric_loss on [H, W, 3] CPU images (the trainer's call, fused C++ pass) against
    the composition of l1_loss and ssim, value and gradient, float64."""
    g = torch.Generator().manual_seed(11)
    render = torch.rand(24, 31, 3, generator=g, dtype=torch.float64, requires_grad=True)
    target = torch.rand(24, 31, 3, generator=g, dtype=torch.float64)
    loss, l1, s = photometric_loss(render, target, 0.2)
    ref = 0.8 * l1_loss(render, target) + 0.2 * (1 - ssim(render, target))
    torch.testing.assert_close(loss, ref, rtol=1e-12, atol=1e-12)
    (g_got,) = torch.autograd.grad(loss, render)
    (g_ref,) = torch.autograd.grad(ref, render)
    torch.testing.assert_close(g_got, g_ref, rtol=1e-12, atol=1e-12 * g_ref.abs().max().item())


def test_training_loss_is_the_photometric_loss_and_its_statistics():
    """The trainer's loss object (a CUDA graph on CUDA only): the 3DGS loss and the logged L1,
    SSIM and MSE of the render, with the loss's gradient; off CUDA it never builds a graph."""
    from splat_train.losses import TrainingLoss, photometric_loss

    g = torch.Generator().manual_seed(0)
    target = torch.rand(24, 32, 3, generator=g, dtype=torch.float64)
    render = (target + 0.1 * torch.randn(24, 32, 3, generator=g, dtype=torch.float64)).clamp(0, 1)
    fn = TrainingLoss(0.2, torch.device("cpu"), graphs=True)
    assert not fn.use_graphs
    r1 = render.clone().requires_grad_(True)
    loss, stats = fn(r1, target)
    r2 = render.clone().requires_grad_(True)
    ref, l1, s = photometric_loss(r2, target, 0.2)
    assert loss.item() == ref.item() and not stats.requires_grad
    assert stats.tolist() == [l1.item(), s.item(), ((render - target) ** 2).mean().item()]
    loss.backward()
    ref.backward()
    assert torch.equal(r1.grad, r2.grad)


def test_training_loss_graph_is_built_once_per_shape_and_checked(monkeypatch, caplog):
    """The CUDA-graph path of the trainer's loss, with torch.cuda.make_graphed_callables stood
    in for on the CPU: one capture per image shape, the op-by-op loss and statistics; a graph
    that disagrees with them switches graphs off for the run with a warning."""
    from splat_train.losses import TrainingLoss

    captured = []

    def make_graphed(fn, sample):
        captured.append(tuple(a.shape for a in sample))
        return lambda *args: fn(*args)

    monkeypatch.setattr(torch.cuda, "make_graphed_callables", make_graphed)
    fn, ref = TrainingLoss(0.2, torch.device("cpu")), TrainingLoss(0.2, torch.device("cpu"), graphs=False)
    fn.use_graphs = True
    g = torch.Generator().manual_seed(0)
    for shape in ((24, 32, 3), (24, 32, 3), (12, 16, 3)):
        target = torch.rand(*shape, generator=g, dtype=torch.float64)
        render = (target + 0.1 * torch.randn(*shape, generator=g, dtype=torch.float64)).clamp(0, 1)
        got, want = fn(render.clone().requires_grad_(True), target), ref(render.clone().requires_grad_(True), target)
        assert got[0].item() == want[0].item() and torch.equal(got[1], want[1])
    assert captured == [((24, 32, 3), (24, 32, 3)), ((12, 16, 3), (12, 16, 3))]
    monkeypatch.setattr(torch.cuda, "make_graphed_callables", lambda f, sample: lambda *a: (f(*a)[0] * 2, f(*a)[1]))
    bad = TrainingLoss(0.2, torch.device("cpu"))
    bad.use_graphs = True
    with caplog.at_level("WARNING"):
        loss, _ = bad(render.clone().requires_grad_(True), target)
    assert "training loss as a CUDA graph unavailable" in caplog.text and not bad.use_graphs
    assert loss.item() == ref(render.clone().requires_grad_(True), target)[0].item()
