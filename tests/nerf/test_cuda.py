"""The model on a GPU against the same model on the CPU: one whole window fit (colour phase with pose
refinement, panoptic phase, validation renders) on each device from the same seed. Marked `cuda`: run with
`pytest -m cuda` on a GPU machine, skipped elsewhere."""
import numpy as np
import pytest
import torch

from nerf.config import PanopticConfig, preset
from nerf.fit import fit_panoptic_window
from nerf.panoptic.labels import WindowLabels
from nerf.window import WindowData

pytestmark = pytest.mark.cuda

COLOUR = dict(steps=150, rays_per_step=512, occupancy_every=20, val_register_every=50, val_register_steps=2,
              pose_warmup_steps=20, n_levels=6, log2_capacity=12)
PANOPTIC = PanopticConfig(steps=40, rays_per_frame=64, frames_per_step=2)
FRUITS = [((-0.12, 0.02, 0.9), 0.07, (200, 40, 30), 4), ((0.05, -0.05, 1.0), 0.06, (60, 170, 50), 2),
          ((0.22, 0.04, 0.95), 0.08, (210, 120, 40), 3)]
"""(centre m, radius m, colour, semantic class) of the spheres in front of the wall; instance = index + 1."""
WALL_Z = 1.4


def sphere_window(n: int = 6, w: int = 48, h: int = 32) -> tuple[WindowData, np.ndarray, np.ndarray]:
    """A window of n frames (odd ones train) sliding sideways past three coloured spheres before a textured wall,
    ray-cast analytically (so the GPU machine needs no Open3D): (WindowData, semantic, instance) [n, h, w]."""
    f = 0.9 * w
    u, v = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    d = np.stack([(u - w / 2) / f, (v - h / 2) / f, np.ones_like(u)], -1)
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    rgbs, depths, sems, insts, poses = [], [], [], [], []
    for i in range(n):
        o = np.array([0.03 * i - 0.08, 0.0, 0.0])
        t = (WALL_Z - o[2]) / d[..., 2]
        p = o + t[..., None] * d
        wall = 110 + 60 * ((np.floor(p[..., 0] / 0.05) + np.floor(p[..., 1] / 0.05)) % 2) + 30 * np.sin(40 * p[..., 0])
        rgb, sem, inst = np.repeat(wall[..., None], 3, -1), np.zeros((h, w), np.uint8), np.zeros((h, w), np.int32)
        for k, (c, r, colour, klass) in enumerate(FRUITS):
            oc = o - np.array(c)
            b = (d * oc).sum(-1)
            disc = b ** 2 - (oc ** 2).sum() + r ** 2
            ts = np.where(disc > 0, -b - np.sqrt(np.maximum(disc, 0)), np.inf)
            hit = ts < t
            normal = (o + ts[..., None] * d - np.array(c)) / r
            shade = np.clip(-(normal * d).sum(-1), 0.2, 1.0)[..., None]
            rgb = np.where(hit[..., None], shade * np.array(colour), rgb)
            t, sem, inst = np.where(hit, ts, t), np.where(hit, klass, sem), np.where(hit, k + 1, inst)
        c2w = np.eye(4)
        c2w[:3, 3] = o
        rgbs.append(np.clip(rgb, 0, 255).astype(np.uint8))
        depths.append((t * d[..., 2]).astype(np.float32))
        sems.append(sem.astype(np.uint8))
        insts.append(inst)
        poses.append(c2w)
    data = WindowData(np.stack(rgbs), np.stack(depths), np.tile([f, f, w / 2, h / 2], (n, 1)), np.stack(poses),
                      np.arange(n) % 2 == 1, np.arange(n))
    return data, np.stack(sems), np.stack(insts)


@pytest.fixture(scope="module")
def fits():
    data, sem, inst = sphere_window()
    out = {}
    for device in ("cpu", "cuda"):
        torch.manual_seed(0)
        out[device] = fit_panoptic_window(data, WindowLabels(sem, inst), preset("cpu", **COLOUR), PANOPTIC,
                                          device=device)
    return data, sem, out


def test_a_window_fitted_on_the_gpu_reaches_the_psnr_of_its_cpu_fit(fits):
    _, _, fit = fits
    cpu, gpu = fit["cpu"].colour.val_psnr, fit["cuda"].colour.val_psnr
    assert sorted(cpu) == sorted(gpu)
    assert np.mean(list(gpu.values())) > np.mean(list(cpu.values())) - 0.5, (gpu, cpu)


def on_host(x) -> np.ndarray:
    """A render's image as a numpy array, after checking that it lies in host memory."""
    if isinstance(x, torch.Tensor):
        assert x.device.type == "cpu", x.device
        return x.numpy()
    assert isinstance(x, np.ndarray), type(x)
    return x


def test_the_gpu_fits_renders_lie_on_the_host_and_agree_with_the_cpu_fits(fits):
    data, sem, fit = fits
    cpu, gpu = fit["cpu"].colour.renders, fit["cuda"].colour.renders
    assert sorted(cpu) == sorted(gpu)
    for i in cpu:
        c, g = ({k: on_host(r[k]) for k in ("rgb", "depth", "semantic", "instance")} for r in (cpu[i], gpu[i]))
        assert all(g[k].shape == c[k].shape for k in c)
        assert (g["semantic"] == sem[i]).mean() > (c["semantic"] == sem[i]).mean() - 0.05
        depth_error = [np.median(np.abs(r["depth"] - data.depths[i])) for r in (g, c)]   # metres
        assert depth_error[0] < 1.5 * depth_error[1] + 0.01, depth_error
    assert np.abs(fit["cuda"].colour.poses_c2w - fit["cpu"].colour.poses_c2w)[:, :3, 3].max() < 0.01
