"""A tiny ray-cast glasshouse window (the synthetic row's own scene code) for trainer tests."""
import numpy as np

from nerf.window import WindowData
from stages import synth
from synthetic import render, scene, trajectory

SHORT_FIT = dict(steps=100, rays_per_step=256, occupancy_every=20, val_register_every=30, val_register_steps=2,
                 pose_warmup_steps=20, n_levels=6, log2_capacity=12)
"""preset overrides of a colour fit of tiny_window() that learns it visibly within a few seconds (poses refined
from step 20)."""


def tiny_window(n=6, w=40, h=24, seed=0, labels=False):
    """WindowData of n frames (odd ones train); with labels=True also the ground-truth semantic and
    instance images [n, h, w]."""
    cfg = synth.Config(width=w, height=h, n_frames=n, seed=seed)
    k = synth.intrinsics(cfg)
    poses = []
    for i in range(n):
        p = trajectory.camera_extrinsic(0.35, 0.1).copy()
        p[0, 3] = 0.1 + 0.02 * i
        p[2, 3] += 0.4
        poses.append(p)
    poses = np.stack(poses)
    layout = synth.row_layout(cfg, poses[:, 0, 3], float(poses[0, 1, 3]), float(poses[0, 2, 3]), k)
    sc = scene.build_scene(layout, seed)
    frames = [render.render(sc, p, k, w, h, 1) for p in poses]
    data = WindowData(np.stack([f["rgb"] for f in frames]), np.stack([f["depth"] for f in frames]),
                      np.tile([k[0, 0], k[1, 1], k[0, 2], k[1, 2]], (n, 1)), poses, np.arange(n) % 2 == 1,
                      np.arange(n))
    if labels:
        return data, np.stack([f["semantic"] for f in frames]), np.stack([f["instance"] for f in frames]).astype(np.int32)
    return data
