import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parents[1] / "nerf"))
from scene_fixture import tiny_window  # noqa: E402

from bench.skips import _render_modes, _without_things  # noqa: E402
from nerf.config import preset  # noqa: E402
from nerf.panoptic.labels import WindowLabels  # noqa: E402
from nerf.trainer import fit_window  # noqa: E402


def test_without_things_turns_every_detection_into_a_miss():
    sem = np.array([[[0, 1, 2, 4, 255]]], np.uint8)
    lab = WindowLabels(sem, np.array([[[0, 0, 1, 2, 0]]], np.int32), np.array([[1, 0.8, 0.6]], np.float32))
    bare = _without_things(lab)
    assert bare.semantic.tolist() == [[[0, 1, 1, 1, 255]]]
    assert (bare.instance == 0).all() and bare.confidence.tolist() == [[[1, 1, 1, 1, 0]]]


def test_each_render_skip_evaluates_fewer_samples_and_keeps_the_image():
    data = tiny_window(n=6, w=40, h=24)
    # a 40-step model of a 40 x 24 scene (PSNR about 11 dB): with 2 features and uniform batches its renders
    # with and without skipping differ by 0.7 dB, with the cpu preset's 4 features and edge rays by 1.3 dB
    # (floaters in cells the grid calls empty), and with the cpu preset's light depth loss (0.02, sized for
    # 1200 steps) by 1.0 dB, with the cpu preset's 32-wide decoders by 2.1 dB; the skips are measured on the
    # default row by `pag bench render`. The marching step is three pixel footprints, as the default cone angle
    # is on a 320 px wide image
    cone = 3.0 / float(np.mean(data.intrinsics[:, 0]))
    res = fit_window(data, preset("cpu", steps=40, rays_per_step=256, n_levels=6, n_features=2, log2_capacity=12,
                                  edge_ray_share=0.0, refine_poses=False, depth_loss_weight=0.1, cone_angle=cone,
                                  hidden=64),
                     render_val=False)
    model = res.model
    r = _render_modes(model, data, repeats=1)
    on, off = r["all skips"], r["no occupancy skipping"]
    assert on["samples_per_ray"] < off["samples_per_ray"] and abs(on["psnr"] - off["psnr"]) < 1.0
    assert model.cfg.skip_empty and model.cfg.early_stop_transmittance > 0  # settings restored
    # in this tiny scene the occupied samples end within the first round anyway; early termination shows
    # its saving where rays have samples behind the surface, as with dense marching
    model.cfg = replace(model.cfg, skip_empty=False)
    r = _render_modes(model, data, repeats=1)
    on, off = r["all skips"], r["no early termination"]
    assert on["samples_per_ray"] < off["samples_per_ray"] and abs(on["psnr"] - off["psnr"]) < 1.0
