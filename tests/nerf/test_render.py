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


def packed_batch(counts, seed=0):
    """Packed samples of rays with `counts` samples each: densities over 8 decades, colours, depths, lengths."""
    from nerf.render import Samples

    g = torch.Generator().manual_seed(seed)
    ray = torch.repeat_interleave(torch.arange(len(counts)), torch.tensor(counts))
    n = len(ray)
    sigma = torch.exp(torch.randn(n, generator=g) * 4)
    rgb = torch.rand(n, 3, generator=g)
    s = Samples(ray, torch.rand(n, generator=g) * 3, torch.rand(n, generator=g) * 0.05, len(counts))
    return sigma, rgb, s


def composite_and_grads(sigma, rgb, s, fused, seed=1):
    """composite()'s outputs and the gradients of a random linear function of all three."""
    from nerf.render import composite

    sigma, rgb = sigma.clone().requires_grad_(), rgb.clone().requires_grad_()
    out = composite(sigma, rgb, s, fused=fused)
    g = torch.Generator().manual_seed(seed)
    sum(torch.sum(o * torch.randn(o.shape, generator=g)) for o in out).backward()
    return [o.detach() for o in out] + [sigma.grad, rgb.grad]


def test_fused_compositing_equals_reference_with_gradients():
    import pytest

    from nerf.render import _packed_ext

    sigma, rgb, s = packed_batch([5, 0, 40, 1, 17, 0, 63, 2] * 30)
    sigma[3], s.delta[3] = float("inf"), 0.0         # inf * 0: no optical depth
    sigma[50] = float("inf")                          # opaque: everything behind it has no weight
    if _packed_ext(sigma, rgb) is None:
        pytest.skip("no C++ toolchain here: the fused kernel is unavailable")
    ref = composite_and_grads(sigma, rgb, s, fused=False)
    new = composite_and_grads(sigma, rgb, s, fused=True)
    for name, a, b in zip(["colour", "depth", "left", "d sigma", "d rgb"], ref, new):
        assert torch.isfinite(b).all(), name
        assert torch.allclose(a, b, rtol=1e-4, atol=1e-6), (name, float((a - b).abs().max()))
    assert new[2][1] == 1 and new[0][1].abs().sum() == 0      # a ray without samples


def test_fused_compositing_falls_back_off_cpu_float32():
    from nerf.render import _packed_ext

    sigma, rgb, _ = packed_batch([3, 2])
    assert _packed_ext(sigma.double(), rgb.double()) is None
    assert _packed_ext(sigma, rgb[:, :2]) is None


def test_fused_compositing_rejects_unsorted_rays():
    import pytest

    from nerf.render import _packed_ext

    sigma, rgb, s = packed_batch([3, 2])
    ext = _packed_ext(sigma, rgb)
    if ext is None:
        pytest.skip("no C++ toolchain here: the fused kernel is unavailable")
    with pytest.raises(RuntimeError, match="non-decreasing"):
        ext.composite_forward(sigma, s.delta, rgb, s.t_mid, s.ray_index.flip(0).contiguous(), s.n_rays)


def test_fused_ray_points_equal_reference_with_gradients():
    import pytest

    from nerf.render import _packed_ext, ray_points

    _, _, s = packed_batch([5, 0, 40, 1, 17] * 20, seed=2)
    g = torch.Generator().manual_seed(3)
    o, d = torch.randn(s.n_rays, 3, generator=g), torch.randn(s.n_rays, 3, generator=g)
    if _packed_ext(o, d) is None:
        pytest.skip("no C++ toolchain here: the fused kernel is unavailable")
    for with_dirs in (True, False):
        got = []
        for fused in (False, True):
            oo, dd = o.clone().requires_grad_(), d.clone().requires_grad_()
            x, dn = ray_points(oo, dd, s, with_dirs=with_dirs, fused=fused)
            gx = torch.randn(x.shape, generator=torch.Generator().manual_seed(4))
            loss = (x * gx).sum() + ((dn * gx.flip(0)).sum() if with_dirs else 0)
            loss.backward()
            got.append([x.detach(), dn, oo.grad, dd.grad])
        assert (got[1][1] is None) == (not with_dirs)
        for name, a, b in zip(["x", "dn", "d o", "d d"], *got):
            if a is not None:
                assert torch.allclose(a.detach(), b.detach(), rtol=1e-4, atol=1e-5), (name, with_dirs)
