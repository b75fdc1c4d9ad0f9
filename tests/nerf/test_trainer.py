import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

sys.path.insert(0, str(Path(__file__).parent))
from scene_fixture import SHORT_FIT as FAST  # noqa: E402

from nerf.config import preset  # noqa: E402
from nerf.model import NerfModel  # noqa: E402
from nerf.trainer import NonFiniteLoss, fit_window  # noqa: E402


def test_fit_learns_the_window_and_reloads(window, short_fit, tmp_path):
    res = short_fit
    first, last = res.history[0]["psnr"], res.history[-1]["psnr"]
    assert last > first + 1.5
    assert np.isfinite(list(res.val_psnr.values())).all() and res.samples_per_ray > 0
    assert res.poses_c2w.shape == (6, 4, 4) and np.isfinite(res.poses_c2w).all()
    torch.save(res.model.state(), tmp_path / "ckpt.pt")
    again = NerfModel.from_state(torch.load(tmp_path / "ckpt.pt", weights_only=False))
    a = res.model.render_image(1)["rgb"]
    b = again.render_image(1)["rgb"]
    assert torch.allclose(a, b, atol=1e-5)


def test_skipping_evaluates_fewer_samples_than_dense_marching(window):
    cfg = preset("cpu", **FAST, refine_poses=False)
    skip = fit_window(window, replace(cfg, steps=30))
    dense = fit_window(window, replace(cfg, steps=30, skip_empty=False, early_stop_transmittance=0.0))
    assert skip.samples_per_ray * 2 < dense.samples_per_ray
    # early termination alone (dense marching, so rays have samples behind the surface): the same model
    # rendered with rays marched to the far plane
    model = skip.model
    model.cfg = replace(model.cfg, skip_empty=False)
    stop = model.render_image(1)
    model.cfg = replace(model.cfg, early_stop_transmittance=0.0)
    full = model.render_image(1)
    assert stop["samples_per_ray"] < full["samples_per_ray"]
    assert torch.allclose(stop["rgb"], full["rgb"], atol=2e-2)


def test_non_finite_loss_names_the_step(window, monkeypatch):
    import nerf.fields.permuto as field_mod

    real = field_mod.RadianceField.forward

    def poisoned(self, x, d, *args):
        sigma, rgb, g = real(self, x, d, *args)
        return sigma, rgb * float("nan"), g

    monkeypatch.setattr(field_mod.RadianceField, "forward", poisoned)
    with pytest.raises(NonFiniteLoss, match="at step 0"):
        fit_window(window, preset("cpu", **FAST))


def test_fixed_poses_stay_fixed_when_refinement_is_off(window):
    cfg = preset("cpu", **{**FAST, "steps": 25, "pose_warmup_steps": 0, "lr_pose": 1e-2})
    res = fit_window(window, replace(cfg, refine_poses=False))
    assert np.allclose(res.poses_c2w, window.poses_c2w, atol=1e-6)


def test_depth_loss_skips_depth_edges_and_pixels_next_to_lost_depth():
    from nerf.trainer import depth_supervised

    d = torch.full((1, 6, 7), 0.5)
    d[0, :, 4:] = 1.0          # a step of 0.5 m between columns 3 and 4
    d[0, 5, 0] = 0.0           # one pixel without depth
    d[0, 0, 6] = 9.0           # beyond the far plane
    ok = depth_supervised(d, 0.05, 3.5)
    assert not ok[0, :, 3:5].any()                               # both sides of the step
    assert ok[0, 0:4, 0:3].all() and ok[0, 2:, 5:].all()          # flat parts keep it
    assert not ok[0, 4:, 0:2].any() and not ok[0, 5, 0]           # the lost pixel and its neighbours
    assert not ok[0, 0, 6] and not ok[0, 1, 5]                    # beyond far: no target, and an edge
    plain = depth_supervised(d, 0.0, 3.5)                        # edge_m 0: every valid pixel below far
    assert plain.sum() == 6 * 7 - 2 and plain[0, :, 3:5].all()
    assert depth_supervised(d, 1.0, 3.5)[0, :, 3:5].all()         # a step below edge_m is no edge


def test_the_depth_range_by_opencv_equals_max_pooling():
    """depth_supervised's CPU path (dilate - erode) gives max pooling's values, border pixels and invalid (0)
    neighbours included."""
    import numpy as np

    from nerf.trainer import depth_range_3x3, depth_range_3x3_pooled

    g = np.random.default_rng(2)
    for shape in [(72, 128), (5, 7), (1, 1), (2, 9)]:
        d = torch.from_numpy((g.random(shape) * 4).astype(np.float32))
        d[d < 0.6] = 0
        assert torch.equal(depth_range_3x3(d), depth_range_3x3_pooled(d))
    step = torch.zeros(3, 4)
    step[:, 2:] = 1.0
    assert depth_range_3x3(step).tolist() == [[0, 1, 1, 0]] * 3                # the border has no outside


def test_edge_ray_share_fits(window):
    cfg = preset("cpu", **{**FAST, "steps": 30}, edge_ray_share=0.5, refine_poses=False)
    res = fit_window(window, cfg, render_val=False)
    assert np.isfinite(res.train_psnr) and res.history[-1]["samples_per_ray"] > 0


def test_registration_anneals_its_rate_draws_rays_on_texture_and_restores_the_rate(window, short_fit, monkeypatch):
    import nerf.trainer as trainer
    from nerf.pixel_sampling import gradient_cdf
    from nerf.poses import PoseCorrection

    model = short_fit.model
    images = torch.from_numpy(window.images).clone()
    val = torch.from_numpy(np.flatnonzero(~window.is_train))
    images[val] = 40
    images[val[0], :, 20:] = 220             # the only texture: a vertical edge in the first validation frame
    drawn, rates = [], []
    real = trainer._rays_for

    def spy(model_, poses_, c2w0, k, frames, u, v, attach):
        drawn.append((frames.clone(), u.clone()))
        rates.append(opt.param_groups[0]["lr"])
        return real(model_, poses_, c2w0, k, frames, u, v, attach)

    monkeypatch.setattr(trainer, "_rays_for", spy)
    poses = PoseCorrection(len(images), model.scene.scale_m)
    opt = torch.optim.Adam(poses.parameters(), lr=1e-3)
    k = torch.tensor(window.intrinsics, dtype=torch.float32)
    trainer.register(model, poses, opt, model.poses_c2w.clone(), k, images, val, 5, torch.Generator().manual_seed(0),
                     rays=200, anneal=0.1, edge_cdf=gradient_cdf(images[val]), edge_share=0.5)
    assert np.allclose(rates, [1e-3 * 0.1 ** (i / 4) for i in range(5)])
    assert opt.param_groups[0]["lr"] == 1e-3                          # restored for the next registration
    frames, u = torch.cat([f[:100] for f, _ in drawn]), torch.cat([u_[:100] for _, u_ in drawn]) - 0.5
    assert ((frames == val[0]) & ((u == 19) | (u == 20))).float().mean() > 0.8
    frames = torch.cat([f[100:] for f, _ in drawn])                    # the other half: every validation frame
    assert set(frames.tolist()) == set(val.tolist())


def test_a_checkpoint_with_the_old_pixel_footprint_step_loads_with_the_same_step(short_fit):
    state = short_fit.model.state()
    fx = float(state["intrinsics"][:, 0].mean())
    old = {**state, "cfg": {k: v for k, v in state["cfg"].items() if k != "cone_angle"} | {"step_scale": 3.0}}
    again = NerfModel.from_state(old)
    assert again.cfg.cone_angle == pytest.approx(3.0 / fx)
    edges = again.edges(torch.device("cpu"))
    assert torch.allclose((edges[1:] - edges[:-1])[:-1], edges[:-2] * 3.0 / fx, rtol=1e-4)  # the last one ends at far


def test_the_marching_step_is_the_same_for_every_image_size_and_render_scale(short_fit):
    from nerf.render_scale import scaled_model

    model = short_fit.model
    small = scaled_model(model, 0.5)
    assert small.wh != model.wh and torch.equal(small.edges(torch.device("cpu")), model.edges(torch.device("cpu")))
    with pytest.raises(ValueError, match="cone_angle"):
        preset("cpu", cone_angle=0.0)


def test_rays_per_step_grow_with_the_image_area_above_the_base_size():
    from nerf.config import BASE_PIXELS

    cfg = preset("cpu")
    assert cfg.rays_for(64 * 40) == cfg.rays_for(BASE_PIXELS) == cfg.rays_per_step
    assert cfg.rays_for(1280 * 720) == 2 * cfg.rays_per_step  # 16 x the pixels, to the power 1/4
    assert cfg.rays_for(640 * 360) == round(cfg.rays_per_step * 2 ** 0.5)
    assert preset("cpu", rays_area_exponent=0.0).rays_for(1280 * 720) == cfg.rays_per_step
    with pytest.raises(ValueError, match="rays_area_exponent"):
        preset("cpu", rays_area_exponent=-1.0)


def test_a_large_image_trains_on_more_rays_per_step(window, monkeypatch):
    import nerf.trainer as trainer

    drawn = []
    real = trainer.draw_pixels

    def spy(idx, n, *args, **kw):
        drawn.append(n)
        return real(idx, n, *args, **kw)

    monkeypatch.setattr(trainer, "draw_pixels", spy)
    # the tiny window is 40 x 24 px: with a base size of 60 px it is 16 times larger
    monkeypatch.setattr("nerf.config.BASE_PIXELS", 60)
    fit_window(window, preset("cpu", **{**FAST, "steps": 2}), render_val=False)
    assert drawn[:2] == [2 * FAST["rays_per_step"]] * 2  # the two training steps (validation registration follows)


def test_shift_penalty_keeps_camera_centres_and_still_turns_the_cameras(window):
    from nerf.geometry import rotation_angle_deg

    cfg = preset("cpu", **{**FAST, "steps": 40, "pose_warmup_steps": 0, "lr_pose": 3e-3})
    free = fit_window(window, replace(cfg, pose_shift_penalty=0.0), render_val=False)
    held = fit_window(window, replace(cfg, pose_shift_penalty=1e4), render_val=False)

    def moved(res):
        shift = np.linalg.norm(res.poses_c2w[:, :3, 3] - window.poses_c2w[:, :3, 3], axis=1)
        return shift.mean(), rotation_angle_deg(window.poses_c2w[:, :3, :3], res.poses_c2w[:, :3, :3]).mean()

    (shift_free, turn_free), (shift_held, turn_held) = moved(free), moved(held)
    assert shift_free > 1e-3                       # without it the centres move (by centimetres at this rate)
    assert shift_held < 0.25 * shift_free          # with it they stay near the initial poses
    # orientations are still refined (a fit without refinement turns no camera at all); held positions leave
    # them less to correct, so they turn less than when the centres move too
    assert turn_held > 0.1 * turn_free and turn_held > 0.05
    # the fit weighs the shifts by the window's parallax (shift_weight) and says so
    from nerf.trainer import shift_weight
    assert held.shift_weight == pytest.approx(shift_weight(replace(cfg, pose_shift_penalty=1e4), window.depths))
    assert held.shift_weight > 0 and free.shift_weight == 0.0
