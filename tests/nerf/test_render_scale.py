"""Renders at a working scale (nerf/render_scale.py): scaled intrinsics, stored at full size."""
from dataclasses import dataclass

import numpy as np
import pytest
import torch

from nerf.render import pixel_rays
from nerf.render_scale import render_at, scaled_model, to_full_size, working_scale


@dataclass
class Cam:
    """The two fields scaled_model changes (a stand-in for nerf.trainer.NerfModel, also a dataclass)."""
    intrinsics: torch.Tensor
    wh: tuple[int, int]


def test_scaled_model_sees_the_same_rays_through_the_same_image_points():
    cam = Cam(torch.tensor([[50.0, 52.0, 32.0, 20.0], [60.0, 60.0, 31.0, 19.5]]), (64, 40))
    half = scaled_model(cam, 0.5)
    assert half.wh == (32, 20) and cam.wh == (64, 40)  # the original is untouched
    u, v = torch.tensor([0.5, 17.25, 63.5]), torch.tensor([0.5, 9.0, 39.5])  # full-size image coordinates
    c2w = torch.eye(4).expand(3, 4, 4)
    for i in range(2):
        _, d_full = pixel_rays(cam.intrinsics[i].expand(3, 4), c2w, u, v)
        _, d_half = pixel_rays(half.intrinsics[i].expand(3, 4), c2w, u * 0.5, v * 0.5)
        assert torch.allclose(d_full, d_half, atol=1e-6)


def test_to_full_size_keeps_types_and_invents_no_labels_or_depths():
    rng = np.random.default_rng(0)
    out = {"rgb": torch.rand(20, 32, 3), "depth": torch.rand(20, 32), "opacity": torch.rand(20, 32),
           "semantic": rng.integers(0, 5, (20, 32)).astype(np.uint8),
           "instance": rng.integers(0, 300, (20, 32)).astype(np.int32), "samples_per_ray": 3.0}
    full = to_full_size(out, (64, 40))
    assert full["rgb"].shape == (40, 64, 3) and isinstance(full["rgb"], torch.Tensor)
    assert full["instance"].dtype == np.int32 and full["instance"].shape == (40, 64)
    assert set(np.unique(full["instance"])) <= set(np.unique(out["instance"]))
    assert set(np.unique(full["semantic"])) <= set(np.unique(out["semantic"]))
    assert set(full["depth"].numpy().ravel()) <= set(out["depth"].numpy().ravel())  # nearest: no mixed depths
    assert full["samples_per_ray"] == 3.0


def test_render_at_renders_every_frame_small_and_returns_it_at_full_size():
    cam = Cam(torch.tensor([[50.0, 50.0, 32.0, 20.0]] * 3), (64, 40))
    seen = []

    def render(model, i):
        w, h = model.wh
        seen.append((i, model.wh))
        return {"rgb": torch.zeros(h, w, 3), "depth": torch.zeros(h, w), "semantic": np.zeros((h, w), np.uint8),
                "instance": np.zeros((h, w), np.int32), "samples_per_ray": 1.0}

    fn = render_at(render, cam, 0.25)
    outs = [fn(i) for i in range(3)]
    assert all(o["rgb"].shape == (40, 64, 3) and o["instance"].shape == (40, 64) for o in outs)
    assert seen == [(0, (16, 10)), (1, (16, 10)), (2, (16, 10))]
    # a resized render keeps its colour at the working scale (validation PSNR is measured there)
    assert all(o["rgb_working"].shape == (10, 16, 3) for o in outs)
    seen.clear()
    out = render_at(render, cam, 1.0)(0)
    assert seen == [(0, (64, 40))] and "rgb_working" not in out


def test_automatic_render_scale_keeps_renders_at_most_320_px_wide():
    assert working_scale(0, 160) == 1 and working_scale(0, 320) == 1
    assert working_scale(0, 640) == 0.5 and working_scale(0, 1280) == 0.25
    assert working_scale(0, 1920) == pytest.approx(1 / 6)
    assert working_scale(0.25, 320) == 0.25  # a set scale is kept


def test_validation_psnr_of_a_small_render_is_measured_at_its_scale():
    from types import SimpleNamespace

    from nerf.trainer import validate

    # a recorded image with one-pixel texture: an exact half-size render of its area average scores high at
    # the working scale, where the same render blown up to full size would not
    rng = np.random.default_rng(0)
    image = rng.integers(0, 256, (40, 64, 3)).astype(np.uint8)
    data = SimpleNamespace(is_train=np.array([True, False]), images=np.stack([image, image]),
                           frame_ids=np.array([10, 11]))
    import cv2
    small = torch.from_numpy(cv2.resize(image, (32, 20), interpolation=cv2.INTER_AREA)).float() / 255
    res = SimpleNamespace(renders={}, val_psnr={}, samples_per_ray=0.0, render_s_per_image=0.0)
    cam = Cam(torch.tensor([[50.0, 50.0, 32.0, 20.0]] * 2), (64, 40))
    render = render_at(lambda m, i: {"rgb": small, "samples_per_ray": 1.0}, cam, 0.5)
    validate(res, data, render)
    assert res.val_psnr[11] > 60 and "rgb_working" not in res.renders[1]
    assert res.renders[1]["rgb"].shape == (40, 64, 3)


def test_validation_renders_keep_their_colour_as_the_bytes_that_are_written():
    from types import SimpleNamespace

    from nerf.trainer import validate
    from rowmap.renders import encode

    rng = np.random.default_rng(1)
    rgb = torch.from_numpy(rng.uniform(-0.1, 1.1, (6, 8, 3)).astype(np.float32))
    rgb[0, 0] = torch.tensor([0.5 / 255, 1.5 / 255, 254.5 / 255])  # halves: both roundings go to even
    data = SimpleNamespace(is_train=np.array([True, False]), images=np.zeros((2, 6, 8, 3), np.uint8),
                           frame_ids=np.array([0, 1]))
    res = SimpleNamespace(renders={}, val_psnr={}, samples_per_ray=0.0, render_s_per_image=0.0)
    validate(res, data, lambda i: {"rgb": rgb, "samples_per_ray": 1.0})
    kept = res.renders[1]["rgb"]
    assert kept.dtype == torch.uint8  # a quarter of float32's memory for every validation frame held
    np.testing.assert_array_equal(encode("rgb", kept), encode("rgb", rgb))  # the PNG's bytes are unchanged
    assert res.val_psnr[1] < 10  # PSNR is measured on the float render, before rounding (black target)
