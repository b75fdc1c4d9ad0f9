import numpy as np
import open3d as o3d

from nerf.depth_poses import depth_initial_poses, icp_trajectory, odometry_scale, stretch


def _scene() -> o3d.t.geometry.RaycastingScene:
    """Spheres of several sizes at 0.4-0.8 m in front of a wall at 1.2 m: depth ICP can lock on along x."""
    scene = o3d.t.geometry.RaycastingScene()
    rng = np.random.default_rng(0)
    for x in np.arange(-0.4, 1.2, 0.12):
        s = o3d.geometry.TriangleMesh.create_sphere(radius=rng.uniform(0.02, 0.05), resolution=12)
        s.translate([x, rng.uniform(-0.15, 0.15), rng.uniform(0.4, 0.8)])
        scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(s))
    wall = o3d.geometry.TriangleMesh.create_box(2.5, 1.0, 0.01).translate([-0.8, -0.5, 1.2])
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(wall))
    return scene


def _depths(xs: np.ndarray, k: np.ndarray, w: int = 80, h: int = 60) -> np.ndarray:
    scene = _scene()
    v, u = np.mgrid[0:h, 0:w]
    d = np.stack([(u + 0.5 - k[2]) / k[0], (v + 0.5 - k[3]) / k[1], np.ones((h, w))], -1).reshape(-1, 3)
    out = []
    for x in xs:
        rays = np.concatenate([np.tile([x, 0.0, 0.0], (len(d), 1)), d], 1).astype(np.float32)
        t = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()   # along z = 1 rays: t is the z-depth
        out.append(np.where(np.isfinite(t), t, 0.0).reshape(h, w))
    return np.stack(out).astype(np.float32)


def _poses(xs: np.ndarray) -> np.ndarray:
    c2w = np.tile(np.eye(4), (len(xs), 1, 1))
    c2w[:, 0, 3] = xs
    return c2w


def test_odometry_scale_recovers_a_stretched_odometry_and_stretch_undoes_it():
    xs = np.arange(32) * 0.012                                       # 1.2 cm between frames
    k = np.array([60.0, 60.0, 40.0, 30.0])
    depths, intr = _depths(xs, k), np.tile(k, (len(xs), 1))
    odo = _poses(xs * 1.05 + 0.3)                                    # 5 % long, and offset
    est = odometry_scale(depths, intr, odo)
    assert est.note == "" and est.pairs >= 3 and abs(est.scale - 1 / 1.05) < 0.005
    fixed = stretch(odo, est.scale)[:, 0, 3]
    np.testing.assert_allclose(np.diff(fixed), np.diff(xs), atol=3e-4)
    np.testing.assert_allclose(stretch(odo, 1.0), odo)
    assert abs(odometry_scale(depths, intr, _poses(xs)).scale - 1.0) < 0.005


def test_odometry_scale_stays_at_one_with_a_note_when_depth_cannot_tell():
    xs = np.arange(32) * 0.012
    k = np.array([60.0, 60.0, 40.0, 30.0])
    est = odometry_scale(np.zeros((32, 60, 80), np.float32), np.tile(k, (32, 1)), _poses(xs * 1.05))
    assert est.scale == 1.0 and est.pairs == 0 and "registered" in est.note
    est = odometry_scale(_depths(xs, k), np.tile(k, (32, 1)), _poses(xs * 1.05), max_change=0.01)
    assert est.scale == 1.0 and "off by more than" in est.note


def test_icp_trajectory_recovers_the_shape_of_a_drifting_odometry_in_its_frame():
    xs = np.arange(32) * 0.012
    k = np.array([60.0, 60.0, 40.0, 30.0])
    depths, intr = _depths(xs, k), np.tile(k, (32, 1))
    odo = _poses(xs * 1.05)
    odo[:, 1, 3] += 0.002 * np.arange(32) ** 1.5 / 32 ** 0.5         # a lateral drift that grows
    poses, links, note = icp_trajectory(depths, intr, odo)
    assert links == 31 and note == ""
    steps = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    np.testing.assert_allclose(steps, 0.012, atol=3e-4)               # the true spacing, not the odometry's
    assert abs(poses[:, :3, 3].mean(0) - odo[:, :3, 3].mean(0)).max() < 1e-6   # placed onto the odometry
    np.testing.assert_allclose(poses[:, :3, :3], odo[:, :3, :3], atol=3e-3)  # no roll about the straight track
    blind, links, note = icp_trajectory(np.zeros_like(depths), intr, odo)
    np.testing.assert_allclose(blind, odo, atol=1e-9)                 # nothing to lock on: the odometry
    assert links == 0 and "31 of 31" in note


def test_depth_initial_poses_modes():
    xs = np.arange(32) * 0.012
    k = np.array([60.0, 60.0, 40.0, 30.0])
    depths, intr, odo = _depths(xs, k), np.tile(k, (32, 1)), _poses(xs * 1.05)
    same, info = depth_initial_poses("off", depths, intr, odo)
    assert same is odo and info["depth_poses"] == "off"
    scaled, info = depth_initial_poses("scale", depths, intr, odo)
    assert abs(info["odometry_scale"] - 1 / 1.05) < 0.005 and info["depth_pose_votes"] >= 5
    chained, info = depth_initial_poses("icp", depths, intr, odo)
    assert info["depth_pose_votes"] == 31
    import pytest
    with pytest.raises(ValueError, match="modes"):
        depth_initial_poses("lidar", depths, intr, odo)
