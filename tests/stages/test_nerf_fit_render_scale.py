"""nerf_fit.render_scale: renders at a working scale with scaled intrinsics, stored at full size; labelled
frames at full size."""
from dataclasses import dataclass

import numpy as np
import pytest
import torch

from nerf.render import pixel_rays
from stages import nerf_fit


@dataclass
class Cam:
    """The two fields scaled_model changes (a stand-in for nerf.trainer.NerfModel, also a dataclass)."""
    intrinsics: torch.Tensor
    wh: tuple[int, int]


def test_scaled_model_sees_the_same_rays_through_the_same_image_points():
    cam = Cam(torch.tensor([[50.0, 52.0, 32.0, 20.0], [60.0, 60.0, 31.0, 19.5]]), (64, 40))
    half = nerf_fit.scaled_model(cam, 0.5)
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
    full = nerf_fit.to_full_size(out, (64, 40))
    assert full["rgb"].shape == (40, 64, 3) and isinstance(full["rgb"], torch.Tensor)
    assert full["instance"].dtype == np.int32 and full["instance"].shape == (40, 64)
    assert set(np.unique(full["instance"])) <= set(np.unique(out["instance"]))
    assert set(np.unique(full["semantic"])) <= set(np.unique(out["semantic"]))
    assert set(full["depth"].numpy().ravel()) <= set(out["depth"].numpy().ravel())  # nearest: no mixed depths
    assert full["samples_per_ray"] == 3.0


def test_render_at_renders_labelled_frames_full_size_and_the_others_small():
    cam = Cam(torch.tensor([[50.0, 50.0, 32.0, 20.0]] * 3), (64, 40))
    seen = []

    def render(model, i):
        w, h = model.wh
        seen.append((i, model.wh))
        return {"rgb": torch.zeros(h, w, 3), "depth": torch.zeros(h, w), "semantic": np.zeros((h, w), np.uint8),
                "instance": np.zeros((h, w), np.int32), "samples_per_ray": 1.0}

    fn = nerf_fit.render_at(render, cam, 0.25, full_size={1})
    for i in range(3):
        assert fn(i)["rgb"].shape == (40, 64, 3)
    assert seen == [(0, (16, 10)), (1, (64, 40)), (2, (16, 10))]
    seen.clear()
    nerf_fit.render_at(render, cam, 1.0, full_size=set())(0)
    assert seen == [(0, (64, 40))]


@pytest.mark.parametrize("bad", [0.0, -0.5, 1.5])
def test_render_scale_outside_0_1_is_refused(bad):
    with pytest.raises(ValueError, match="render_scale must be in"):
        nerf_fit.Config(render_scale=bad)
