import warnings

import pytest
import torch

from nerf import _ext
from nerf.encoding import CubicHashEncoding, PermutoEncoding, lattice, permuto_encode_reference

KW = dict(n_levels=8, n_features=2, log2_capacity=10, coarsest_scale=1.0, finest_scale=0.01, init_std=1.0)


def points(n=400, seed=0):
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(n, 3, generator=g) * 2 - 1
    axis = torch.zeros(50, 3)
    axis[:, 0] = torch.linspace(-1, 1, 50)          # a ray parallel to a lattice axis
    far = torch.tensor([[40.0, -30.0, 25.0], [-7.5, 12.0, 3.0]])  # far outside the grid bounds
    return torch.cat([x, axis, far])


def pair(cls):
    fused = cls(**KW, backend="fused")
    ref = cls(**KW, backend="torch")
    ref.load_state_dict(fused.state_dict())
    return fused, ref


@pytest.mark.parametrize("cls", [PermutoEncoding, CubicHashEncoding])
def test_fused_equals_reference_in_values_and_both_gradients(cls):
    if _ext.load_permuto_ext("cpu") is None:
        pytest.skip("no C++ compiler: the fused kernel is unavailable here")
    fused, ref = pair(cls)
    x1 = points().requires_grad_()
    x2 = x1.detach().clone().requires_grad_()
    a, b = fused(x1), ref(x2)
    scale = b.abs().max()
    assert torch.allclose(a, b, atol=1e-4 * float(scale))  # float32 rounding of large lattice coords
    g = torch.randn_like(a)
    a.backward(g)
    b.backward(g)
    assert torch.allclose(fused.table.grad, ref.table.grad, atol=2e-5 * float(ref.table.grad.abs().max()))
    assert torch.allclose(x1.grad, x2.grad, atol=1e-4 * float(x2.grad.abs().max()))
    assert torch.isfinite(x1.grad).all()


def test_barycentric_weights_are_a_partition_of_unity():
    idx, w = lattice(points(), torch.tensor(0.05), torch.tensor([0.1, 0.2, 0.3]), 1023)
    assert torch.allclose(w.sum(1), torch.ones(len(w)), atol=1e-5)
    assert (w >= -1e-6).all() and (w <= 1 + 1e-6).all()
    assert idx.min() >= 0 and idx.max() < 1024


def test_encoding_is_continuous_across_simplex_boundaries():
    enc = PermutoEncoding(**KW, backend="torch")
    t = torch.linspace(0, 1, 4001)[:, None]
    line = torch.tensor([[-0.3, 0.2, 0.1]]) + t * torch.tensor([[0.5, -0.4, 0.3]])
    f = enc(line)
    jumps = (f[1:] - f[:-1]).abs().max()
    assert jumps < 0.05 * f.abs().max()


def test_reference_gradcheck_in_double():
    enc = PermutoEncoding(n_levels=2, log2_capacity=6, finest_scale=0.3, init_std=1.0, backend="torch").double()
    x = (torch.rand(5, 3, dtype=torch.float64) * 0.5).requires_grad_()
    table = enc.table.detach().clone().requires_grad_()
    assert torch.autograd.gradcheck(lambda p, t: permuto_encode_reference(p, t, enc.scales.double(), enc.shifts.double()),
                                    (x, table), eps=1e-6, atol=1e-4)


def test_fallback_warns_once_and_still_works(monkeypatch):
    monkeypatch.setattr(_ext, "_CACHE", {})
    monkeypatch.setattr(_ext, "BUILD_DIR", _ext.BUILD_DIR)

    def broken_load(*a, **k):
        raise OSError("no compiler")

    import torch.utils.cpp_extension as ce
    monkeypatch.setattr(ce, "load", broken_load)
    enc = PermutoEncoding(**KW)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        out1 = enc(points())
        out2 = enc(points())
    msgs = [w for w in caught if "fused permutohedral kernel unavailable" in str(w.message)]
    assert len(msgs) == 1 and torch.equal(out1, out2)
    with pytest.raises(RuntimeError, match="fused kernel is unavailable"):
        PermutoEncoding(**KW, backend="fused")(points())


def test_half_precision_input_and_huge_coordinates_stay_finite():
    enc = PermutoEncoding(**KW)
    x = (points() * 3).half()
    with torch.autocast("cpu", dtype=torch.bfloat16):
        y = enc(x)
    assert y.dtype == torch.float32 and torch.isfinite(y).all()
    for backend in ("torch", "auto"):
        enc.backend = backend
        y = enc(torch.tensor([[float("nan"), float("inf"), -1e30], [1e4, 1e4, -1e4]], requires_grad=True))
        y.sum().backward()
        assert torch.isfinite(y).all() and torch.isfinite(enc.table.grad).all()


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_matches_cpu():
    enc = PermutoEncoding(**KW, backend="torch")
    x = points()
    assert torch.allclose(enc(x), enc.cuda()(x.cuda()).cpu(), atol=1e-4)
