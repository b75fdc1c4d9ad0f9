"""A tiny ray-cast glasshouse window (the synthetic row's own scene code) for trainer tests."""
import numpy as np

from nerf.trainer import WindowData
from synthetic import scene, trajectory


def tiny_window(n=6, w=40, h=24, seed=0) -> WindowData:
    lay = scene.RowLayout(-1.0, 1.5, 0.6, 2.0, 3.0, (0.5, 0.86), 0.3, 12.0)
    sc = scene.build_scene(lay, seed)
    fx = w / 2 / np.tan(np.radians(34.5))
    poses = []
    for i in range(n):
        p = trajectory.camera_extrinsic(0.7).copy()
        p[0, 3] = 0.1 + 0.02 * i
        poses.append(p)
    poses = np.stack(poses)
    frames = [scene.render(sc, p, fx, fx, w / 2, h / 2, w, h, 1) for p in poses]
    return WindowData(np.stack([f["rgb"] for f in frames]), np.stack([f["depth"] for f in frames]),
                      np.tile([fx, fx, w / 2, h / 2], (n, 1)), poses, np.arange(n) % 2 == 1, np.arange(n))
