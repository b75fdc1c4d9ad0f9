"""Which pixels a training step draws (nerf/pixel_sampling.py)."""
import numpy as np
import torch


def test_thing_oversampling_is_undone_by_importance_weights():
    from nerf.pixel_sampling import LabelPixels

    sem = np.ones((40, 50), np.uint8)
    things = np.zeros((40, 50), bool)
    things[:4, :5] = True                        # 1 % of the pixels are fruit
    sem[things] = 4
    px, w = LabelPixels(sem != 255, things).draw(20000, 0.5, np.random.default_rng(0))
    on = things.ravel()[px]
    assert 0.45 < on.mean() < 0.55                # half the rays land on fruit ...
    assert abs((w * on).sum() / w.sum() - 0.01) < 0.003   # ... but weigh as 1 % of the image
    assert w.max() == 1.0 and (w > 0).all()


def scanned_draw(labelled, things, n, share, rng):
    """The draws as the masks say them, each list of pixels scanned out of the masks (the reference)."""
    thing_px, labelled_px = np.flatnonzero(things), np.flatnonzero(labelled)
    pool = labelled_px if labelled_px.size else np.arange(labelled.size)
    n_thing = int(round(n * share)) if thing_px.size else 0
    s = n_thing / n
    picks = [thing_px[rng.integers(0, thing_px.size, n_thing)]] if n_thing else []
    px = np.concatenate(picks + [pool[rng.integers(0, pool.size, n - n_thing)]])
    q = (1 - s) / pool.size + np.where(things.ravel()[px], s / max(thing_px.size, 1), 0.0)
    w = (1.0 / pool.size) / q
    return px, w / w.max()


def test_indexed_frame_draws_what_the_mask_scans_draw():
    from nerf.pixel_sampling import LabelPixels

    g = np.random.default_rng(5)
    labelled = g.random((30, 40)) > 0.2            # a fifth of the pixels unlabelled, scattered
    labelled[0, :7] = labelled[-1, -5:] = False     # runs of them at both ends
    things = labelled & (g.random((30, 40)) > 0.9)
    cases = [(labelled, things), (labelled, np.zeros_like(things)),          # no fruit in the frame
             (np.zeros_like(labelled), np.zeros_like(things)),               # nothing labelled: every pixel
             (np.ones_like(labelled), things)]                               # everything labelled
    for lab, th in cases:
        frame = LabelPixels(lab, th)
        for seed in range(3):
            want = scanned_draw(lab, th, 384, 0.5, np.random.default_rng(seed))
            got = frame.draw(384, 0.5, np.random.default_rng(seed))
            assert np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1])
        assert lab.ravel()[frame.draw(500, 0.5, np.random.default_rng(9))[0]].all() or not lab.any()


def test_edge_rays_are_drawn_where_the_image_has_texture():
    from nerf.pixel_sampling import draw_from_cdf, gradient_cdf

    img = torch.zeros(2, 20, 30, 3, dtype=torch.uint8)
    img[0, :, 15:] = 200            # a vertical edge between columns 14 and 15 of frame 0; frame 1 is flat
    pick = draw_from_cdf(gradient_cdf(img), 4000, torch.Generator().manual_seed(0))
    frame, col = pick // (20 * 30), pick % 30
    on_edge = (frame == 0) & ((col == 14) | (col == 15))
    assert on_edge.float().mean() > 0.8           # 40 of 1200 pixels carry the edge
    assert (frame == 1).any()                     # the floor keeps every pixel drawable


def test_block_cdf_draws_what_a_search_of_the_whole_sum_draws():
    from nerf.pixel_sampling import CDF_BLOCK, GradientCDF, draw_from_cdf

    g = torch.Generator().manual_seed(3)
    weights = torch.rand(7 * CDF_BLOCK + 37, generator=g) ** 4       # a partial last block, weights spanning 1e-8..1
    weights[100:900] = 0.0                                           # whole blocks of zero weight
    cdf = GradientCDF(weights)
    whole = weights.double().cumsum(0)                               # what was searched before blocks
    u = torch.cat([torch.rand(20000, generator=g, dtype=torch.float64) * whole[-1],
                   whole[::97], whole[-1:], torch.zeros(1, dtype=torch.float64), whole[-1:] * 1.5])
    expect = torch.searchsorted(whole, u)
    assert torch.equal(cdf.search(u), expect)                        # every value, exact sums included
    assert torch.equal(draw_from_cdf(cdf, 5000, torch.Generator().manual_seed(1)),
                       torch.searchsorted(whole, torch.rand(5000, generator=torch.Generator().manual_seed(1),
                                                            dtype=torch.float64) * whole[-1]).clamp_max(len(whole) - 1))
    assert cdf.block_end.numel() * CDF_BLOCK >= len(weights) and cdf.weights.dtype == torch.float32


def test_the_gradient_magnitude_in_numpy_is_the_torch_one_bit_for_bit():
    """gradient_cdf's CPU path (numpy, fewer temporaries) gives the same float32 bits as the torch reference,
    so the edge rays a window draws do not depend on which ran; also on images of one or two rows."""
    import numpy as np

    from nerf.pixel_sampling import gradient_magnitude, gradient_magnitude_torch

    g = np.random.default_rng(3)
    for shape in [(72, 128, 3), (5, 7, 3), (1, 1, 3), (2, 9, 3), (6, 4, 1)]:
        im = torch.from_numpy(g.integers(0, 256, shape, dtype=np.uint8))
        fast, ref = gradient_magnitude(im), gradient_magnitude_torch(im)
        assert fast.dtype == torch.float32 and fast.shape == shape[:2] and torch.equal(fast, ref)
    flat = torch.full((4, 4, 3), 9, dtype=torch.uint8)
    assert not gradient_magnitude(flat).any()
