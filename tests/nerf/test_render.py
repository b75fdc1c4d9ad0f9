import math

import torch

from nerf.render import accumulate, composite_weights, cone_steps, march, pixel_rays


def dense_reference(sigma, delta):
    """Textbook per-ray compositing with a cumulative product (test only)."""
    alpha = 1 - torch.exp(-sigma * delta)
    trans = torch.cumprod(torch.cat([torch.ones(1), 1 - alpha[:-1]]), 0)
    return trans * alpha


def test_docstring_example():
    w, left = composite_weights(torch.tensor([1.0, 2.0]), torch.tensor([0.5, 0.5]), torch.tensor([0, 0]), 1)
    assert torch.allclose(w, torch.tensor([0.3935, 0.3834]), atol=1e-4)
    assert math.isclose(float(1 - left[0]), 0.7769, abs_tol=1e-4)


def test_packed_compositing_equals_dense_reference_per_ray():
    g = torch.Generator().manual_seed(0)
    counts = [3, 0, 7, 1, 5]
    ray = torch.cat([torch.full((c,), i) for i, c in enumerate(counts)])
    sigma = torch.rand(len(ray), generator=g) * 5
    delta = torch.rand(len(ray), generator=g) * 0.3
    w, left = composite_weights(sigma, delta, ray, len(counts))
    for i in range(len(counts)):
        m = ray == i
        if m.any():
            assert torch.allclose(w[m], dense_reference(sigma[m], delta[m]), atol=1e-6)
            assert torch.isclose(left[i], torch.exp(-(sigma[m] * delta[m]).sum()))
    assert left[1] == 1


def test_gradients_reach_density_and_colour():
    sigma = torch.tensor([0.5, 3.0, 1.0], requires_grad=True)
    col = torch.rand(3, 3, requires_grad=True)
    ray = torch.tensor([0, 0, 1])
    w, _ = composite_weights(sigma, torch.full((3,), 0.2), ray, 2)
    accumulate(col, w, ray, 2).sum().backward()
    assert sigma.grad.abs().sum() > 0 and col.grad.abs().sum() > 0


def test_huge_density_stays_finite():
    w, left = composite_weights(torch.tensor([1e30, 1e-30, 1e6]), torch.tensor([1.0, 1.0, 1.0]),
                                torch.tensor([0, 0, 0]), 1)
    assert torch.isfinite(w).all() and torch.isclose(w.sum(), torch.tensor(1.0))


def test_rays_have_unit_z_in_camera_and_march_skips_empty():
    k = torch.tensor([[100.0, 100.0, 50.0, 40.0]])
    c2w = torch.eye(4)[None]
    o, d = pixel_rays(k, c2w, torch.tensor([50.0]), torch.tensor([40.0]))
    assert torch.allclose(d, torch.tensor([[0.0, 0.0, 1.0]]))
    edges = cone_steps(0.1, 3.0, 0.02, torch.device("cpu"))
    full = march(o, d, edges, lambda p: torch.ones(len(p), dtype=torch.bool), jitter=False)
    slab = march(o, d, edges, lambda p: (p[:, 2] > 1.0) & (p[:, 2] < 1.2), jitter=False)
    assert len(full) == len(edges) - 1
    assert 0 < len(slab) < len(full) / 5 and ((slab.t_mid > 1.0) & (slab.t_mid < 1.2)).all()


def random_grid(seed=0):
    from nerf.occupancy import OccupancyGrid

    g = torch.Generator().manual_seed(seed)
    grid = OccupancyGrid(torch.tensor([-1.0, -0.5, 0.0]), torch.tensor([1.0, 0.5, 2.5]), 24)
    grid.occupied = torch.rand(grid.occupied.shape[0], generator=g) < 0.3
    return grid


def grid_rays(n=300, seed=0):
    """Rays from inside and outside the grid's bounds, some never entering it, one with zero direction."""
    g = torch.Generator().manual_seed(seed)
    o = torch.rand(n, 3, generator=g) * torch.tensor([3.0, 2.0, 1.0]) - torch.tensor([1.5, 1.0, 0.5])
    d = torch.randn(n, 3, generator=g) * 0.3 + torch.tensor([0.0, 0.0, 1.0])
    d[0] = 0
    d[1] = torch.tensor([0.0, 0.0, -1.0])
    return o, d


def test_fused_march_equals_torch_reference():
    import pytest

    from nerf.render import Rounds, _march_ext

    grid = random_grid()
    o, d = grid_rays()
    if _march_ext(o, grid) is None:
        pytest.skip("no C++ toolchain here: the fused kernel is unavailable")
    edges = cone_steps(0.1, 3.0, 0.03, torch.device("cpu"))
    cases = [dict(jitter=False), dict(jitter=True), dict(jitter=True, max_per_ray=5),
             dict(jitter=False, first=3, max_per_ray=4), dict(jitter=False, first=2)]
    for kw in cases:
        torch.manual_seed(7)
        ref = march(o, d, edges, grid, fused=False, **kw)
        torch.manual_seed(7)
        got = march(o, d, edges, grid, **kw)
        assert len(ref) > 100, kw
        assert torch.equal(got.ray_index, ref.ray_index), kw
        assert torch.equal(got.t_mid, ref.t_mid) and torch.equal(got.delta, ref.delta), kw
    # rendering in rounds: the same samples as packing the candidates once
    rows = torch.arange(0, o.shape[0], 3)
    fused = Rounds(o, d, edges, grid)
    assert fused.fused
    ref = Rounds(o, d, edges, lambda p: grid.query(p))
    for first, n in ((0, 8), (8, 16), (24, 32)):
        a, b = fused.take(rows, first, n), ref.take(rows, first, n)
        assert torch.equal(a.ray_index, b.ray_index) and torch.equal(a.t_mid, b.t_mid) and torch.equal(a.delta, b.delta)


def test_fused_march_rejects_bad_inputs():
    import pytest

    from nerf.render import _march_ext

    grid = random_grid()
    o, d = grid_rays(10)
    ext = _march_ext(o, grid)
    if ext is None:
        pytest.skip("no C++ toolchain here: the fused kernel is unavailable")
    edges = cone_steps(0.1, 3.0, 0.03, torch.device("cpu"))
    with pytest.raises(RuntimeError, match="occupied has"):
        ext.march_occupied(o, d, edges, None, grid.occupied[:-1], grid.lo, grid.cell, grid.res, None, 0, 0)
    with pytest.raises(RuntimeError, match="u must be"):
        ext.march_occupied(o, d, edges, torch.rand(3, 3), grid.occupied, grid.lo, grid.cell, grid.res, None, 0, 0)
