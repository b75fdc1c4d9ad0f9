"""What training samples and what rendering marches: the no-grad transmittance pre-pass, progressive render
rounds."""
import torch

from nerf.render import Samples, composite_weights, transmittance
from nerf.trainer import visible_samples


def test_transmittance_matches_the_compositing_weights():
    g = torch.Generator().manual_seed(1)
    ray = torch.tensor([0, 0, 0, 2, 2, 3])
    sigma, delta = torch.rand(6, generator=g) * 5, torch.rand(6, generator=g)
    t = transmittance(sigma, delta, ray, 4)
    w, _ = composite_weights(sigma, delta, ray, 4)
    assert torch.allclose(t * (1 - torch.exp(-sigma * delta)), w, atol=1e-6)
    assert t[0] == 1 and t[3] == 1 and t[5] == 1                       # first sample of each ray
    assert torch.allclose(transmittance(torch.tensor([1.0, 2.0]), torch.tensor([0.5, 0.5]), torch.tensor([0, 0]), 1),
                          torch.tensor([1.0, 0.6065]), atol=1e-4)


def test_visible_samples_drop_what_hides_behind_an_opaque_sample():
    class Wall:
        """Density 1e4 beyond z = 1 (in normalised units), 0 before."""
        field = type("F", (), {"density": staticmethod(lambda x: torch.where(x[:, 2] > 1.0, 1e4, 0.0))})()
        scene = type("S", (), {"normalise": staticmethod(lambda x: x)})()

    t = torch.linspace(0.05, 2.0, 40)
    s = Samples(torch.zeros(40, dtype=torch.long), t, torch.full((40,), 0.05), 1)
    kept, known = visible_samples(Wall(), torch.zeros(1, 3), torch.tensor([[0.0, 0.0, 1.0]]), s, 1e-3)
    assert known is None                                # no hash grid: nothing to hand on
    assert kept.t_mid.max() > 1.0                       # the first sample inside the wall stays
    assert int((kept.t_mid > 1.0).sum()) == 1 and int((kept.t_mid <= 1.0).sum()) == int((t <= 1.0).sum())


def test_progressive_render_rounds_match_one_big_round(short_fit):
    m = short_fit.model
    k, c2w = m.intrinsics[0], m.poses_c2w[0]
    from nerf.render import pixel_rays
    u = torch.arange(0, 40, 3).float() + 0.5
    v = torch.full_like(u, 12.5)
    o, d = pixel_rays(k.expand(len(u), 4), c2w.expand(len(u), 4, 4), u, v)
    a = m.render_rays(o, d)
    # reference: every occupied sample at once, no early termination
    from nerf.render import accumulate, march
    sm = march(o, d, m.edges(o.device), m.occupied_fn(), jitter=False)
    with torch.no_grad():
        sigma, col, _, _ = m.shade(o, d, sm)
    w, left = composite_weights(sigma, sm.delta, sm.ray_index, sm.n_rays)
    ref = accumulate(col, w, sm.ray_index, sm.n_rays)
    assert torch.allclose(a["rgb"], ref, atol=3e-3) and torch.allclose(a["opacity"], 1 - left, atol=3e-3)
    assert float(a["samples_per_ray"]) <= len(sm) / len(u) + 1e-6        # (a float32 count per ray)


def test_the_panoptic_pass_marches_the_rounds_of_the_colour_render(short_fit):
    """weighted_samples (what the panoptic heads see) takes the same progressive rounds as render_rays: the same
    colour, depth and evaluated samples, and every kept sample carries at least min_weight."""
    from nerf.panoptic.samples import weighted_samples
    from nerf.render import pixel_rays

    m = short_fit.model
    k, c2w = m.intrinsics[1], m.poses_c2w[1]
    v, u = torch.meshgrid(torch.arange(0, 24, 2) + 0.5, torch.arange(0, 40, 2) + 0.5, indexing="ij")
    o, d = pixel_rays(k.expand(u.numel(), 4), c2w.expand(u.numel(), 4, 4), u.reshape(-1), v.reshape(-1))
    ref = m.render_rays(o, d)
    ks = weighted_samples(m, o, d, min_weight=1e-2)
    assert torch.allclose(ks.rgb, ref["rgb"], atol=1e-5)
    assert torch.allclose(ks.opacity, ref["opacity"], atol=1e-5)
    assert ks.n_evaluated == round(float(ref["samples_per_ray"]) * u.numel())
    assert len(ks.w) > 0 and float(ks.w.min()) >= 1e-2
    # the panoptic phase's training steps ask for no colour: the same samples, weights, depth and features
    bare = weighted_samples(m, o, d, min_weight=1e-2, colour=False)
    assert bare.rgb is None
    for name in ("x", "g", "w", "ray_index", "depth", "opacity"):
        assert torch.equal(getattr(bare, name), getattr(ks, name)), name


def test_a_render_colours_only_the_samples_that_can_show():
    """HeavySamples picks the samples whose weight (times the transmittance the ray arrives with) reaches the
    threshold; a field given it decodes colour there, exactly as without it, and leaves 0 elsewhere."""
    from nerf.config import preset
    from nerf.fields.mlp_pe import MlpPeField
    from nerf.fields.permuto import RadianceField
    from nerf.render import HeavySamples

    ray = torch.tensor([0, 0, 0, 1, 1])
    s = Samples(ray, torch.arange(5.0), torch.full((5,), 0.5), 2)
    sigma = torch.tensor([0.0, 40.0, 1.0, 1e-3, 2.0])               # ray 0: opaque second sample; ray 1 half lit
    heavy = HeavySamples(s, torch.tensor([1.0, 0.5]), min_weight=1e-3)
    assert heavy(sigma).tolist() == [False, True, False, False, True]
    w, left = composite_weights(sigma, s.delta, ray, 2)
    assert torch.allclose(heavy.weights, w * torch.tensor([1.0, 1.0, 1.0, 0.5, 0.5])) and torch.equal(heavy.left, left)

    g = torch.Generator().manual_seed(0)
    x = torch.rand(300, 3, generator=g) * 2 - 1
    d = torch.nn.functional.normalize(torch.randn(300, 3, generator=g), dim=-1)
    pick = torch.rand(300, generator=g) < 0.3
    for fld in (RadianceField(preset("cpu", n_levels=4, log2_capacity=10), 1.0), MlpPeField(preset("cpu"), 1.0)):
        with torch.no_grad():
            sig, rgb, _ = fld(x, d)
            sig2, rgb2, _ = fld(x, d, colour_where=lambda s_: pick)
        assert torch.equal(sig, sig2) and torch.equal(rgb2[pick], rgb[pick]) and not rgb2[~pick].any()


def test_a_render_without_the_light_samples_colour_differs_by_their_weight(short_fit, monkeypatch):
    """render_rays colours only samples of weight >= RENDER_COLOUR_MIN_WEIGHT: against colouring every sample
    (threshold 0) depth and opacity stay equal and the colour moves by less than the weight left out."""
    import nerf.render
    from nerf.render import pixel_rays

    m = short_fit.model
    v, u = torch.meshgrid(torch.arange(0, 30, 2) + 0.5, torch.arange(0, 40, 2) + 0.5, indexing="ij")
    o, d = pixel_rays(m.intrinsics[0].expand(u.numel(), 4), m.poses_c2w[0].expand(u.numel(), 4, 4),
                      u.reshape(-1), v.reshape(-1))
    cut = m.render_rays(o, d)
    monkeypatch.setattr(nerf.render, "RENDER_COLOUR_MIN_WEIGHT", 0.0)
    full = m.render_rays(o, d)
    assert torch.equal(cut["depth"], full["depth"]) and torch.equal(cut["opacity"], full["opacity"])
    diff = (cut["rgb"] - full["rgb"]).abs().max()
    assert 0 < diff < 64 * 1e-4            # every sample a ray evaluates may be left out, each under 1e-4


def test_a_training_step_reuses_the_visibility_pass_features(short_fit):
    """visible_samples hands on the grid features of the samples it keeps: the very values a fresh encoding of
    those points gives, and a step shaded with them has the same loss and the same gradients (table and
    decoders; the ray origins a pose moves to float rounding) as one that encodes them again."""
    from nerf.render import composite, march, pixel_rays

    m = short_fit.model
    u = torch.arange(0, 40, 2).float() + 0.5
    o0, d0 = pixel_rays(m.intrinsics[0].expand(len(u), 4), m.poses_c2w[0].expand(len(u), 4, 4), u,
                        torch.full_like(u, 11.5))
    s = march(o0, d0, m.edges(o0.device), m.occupied_fn(), jitter=False)
    # a transmittance bound these rays cross: at 1e-3 the short fit (32-wide decoders) keeps every sample
    kept, known = visible_samples(m, o0, d0, s, 0.1)
    assert known is not None and len(kept) < len(s) and known.shape == (len(kept), m.field.feature_dim)

    def step(features):
        m.field.zero_grad(set_to_none=True)
        o = o0.clone().requires_grad_(True)
        sigma, col, _, g = m.shade(o, d0, kept, grid_features=features)
        loss = composite(sigma, col, kept)[0].square().sum()
        loss.backward()
        return g.detach(), loss.detach(), o.grad, [p.grad.clone() for p in m.field.parameters()]

    fresh, reused = step(None), step(known)
    assert torch.equal(fresh[0], known) and torch.equal(reused[0], known) and torch.equal(fresh[1], reused[1])
    assert all(torch.equal(a, b) for a, b in zip(fresh[3], reused[3]))
    # the position gradient's sums run in per-thread parts: equal to the order of a float sum, as between two
    # fresh steps
    assert torch.allclose(fresh[2], reused[2], rtol=1e-5, atol=1e-5)
