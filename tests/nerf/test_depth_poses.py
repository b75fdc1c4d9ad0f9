import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import nerf.depth_poses as dp
from nerf.depth_poses import depth_initial_poses, icp_trajectory, odometry_scale, stretch
from nerf.geometry import rotation_angle_deg


def _spheres() -> np.ndarray:
    """[14, 4] spheres (x, y, z, radius) of several sizes at 0.4-0.8 m in front of a wall at z = 1.2 m (x in
    [-0.8, 1.7], y in [-0.5, 0.5]): depth ICP can lock on along x."""
    rng = np.random.default_rng(0)
    out = []
    for x in np.arange(-0.4, 1.2, 0.12):
        r = rng.uniform(0.02, 0.05)
        out.append([x, rng.uniform(-0.15, 0.15), rng.uniform(0.4, 0.8), r])
    return np.array(out)


def _render(c2w: np.ndarray, k: np.ndarray, w: int, h: int) -> np.ndarray:
    """Depth [h, w] (metres, 0 = no hit) of the spheres and wall seen by a pinhole camera k = (fx, fy, cx, cy)
    at c2w [4, 4] (OpenCV axes), ray-cast in closed form."""
    v, u = np.mgrid[0:h, 0:w]
    ray = np.stack([(u + 0.5 - k[2]) / k[0], (v + 0.5 - k[3]) / k[1], np.ones((h, w))], -1).reshape(-1, 3)
    d, o = ray @ c2w[:3, :3].T, c2w[:3, 3]              # along a camera-frame ray of z = 1, t is the z-depth
    t = (1.2 - o[2]) / d[:, 2]
    x, y = o[0] + t * d[:, 0], o[1] + t * d[:, 1]
    depth = np.where((t > 0) & (x >= -0.8) & (x <= 1.7) & (y >= -0.5) & (y <= 0.5), t, np.inf)
    a = np.einsum("ij,ij->i", d, d)
    for *c, r in _spheres():
        oc = o - np.array(c)
        b = d @ oc                                      # |o + t d - c|^2 = r^2, nearer root
        disc = b * b - a * (oc @ oc - r * r)
        t = (-b - np.sqrt(np.maximum(disc, 0))) / a
        depth = np.where((disc >= 0) & (t > 0), np.minimum(depth, t), depth)
    return np.where(np.isfinite(depth), depth, 0.0).reshape(h, w).astype(np.float32)


def _depths(xs: np.ndarray, k: np.ndarray, w: int = 80, h: int = 60) -> np.ndarray:
    return np.stack([_render(p, k, w, h) for p in _poses(xs)])


def _poses(xs: np.ndarray) -> np.ndarray:
    c2w = np.tile(np.eye(4), (len(xs), 1, 1))
    c2w[:, 0, 3] = xs
    return c2w


def _moved_pair(w: int = 160, h: int = 120) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(k, depth of camera a, depth of camera b, camera a -> camera b [4, 4]): b is a moved by 2 cm (mostly
    along x) and turned by 1 degree about a tilted axis."""
    k = np.array([0.75 * w, 0.75 * w, w / 2, h / 2])
    axis = np.array([0.3, 1.0, 0.2]) / np.linalg.norm([0.3, 1.0, 0.2])
    move = np.eye(4)
    move[:3, :3], move[:3, 3] = Rotation.from_rotvec(np.deg2rad(1.0) * axis).as_matrix(), [0.0195, 0.003, -0.004]
    a = _poses(np.array([0.1]))[0]
    return k, _render(a, k, w, h), _render(a @ move, k, w, h), np.linalg.inv(move)


def _use(monkeypatch, backend: str) -> None:
    """ICP in `backend` from the next call on: 'numpy' (forced by PAG_ICP) or 'open3d' (the default)."""
    if backend == "numpy":
        monkeypatch.setenv("PAG_ICP", "numpy")
    else:
        monkeypatch.delenv("PAG_ICP", raising=False)
    dp.icp_backend.cache_clear()


@pytest.fixture(autouse=True)
def _fresh_backend():
    """Each test decides ICP's backend afresh and leaves none decided."""
    dp.icp_backend.cache_clear()
    yield
    dp.icp_backend.cache_clear()


@pytest.fixture(params=["open3d", "numpy"])
def icp(request, monkeypatch):
    """Each ICP backend in turn (Open3D skipped where it does not import)."""
    if request.param == "open3d":
        pytest.importorskip("open3d", exc_type=ImportError)
    _use(monkeypatch, request.param)
    return request.param


def test_numpy_icp_recovers_a_small_rigid_motion(monkeypatch):
    _use(monkeypatch, "numpy")
    k, da, db, truth = _moved_pair()
    src, dst = (dp.depth_cloud(d, k, 1.5, 0.004) for d in (da, db))
    assert dp.icp_backend() == "numpy" and len(src.points) > 1000 and len(src.normals) == len(src.points)
    t, fitness = dp.register(src, dst, np.eye(4), max_dist_m=0.03)      # from no motion at all
    assert np.linalg.norm(t[:3, 3] - truth[:3, 3]) < 1e-3 and rotation_angle_deg(t[:3, :3], truth[:3, :3]) < 0.05
    assert fitness > 0.9
    assert dp.register(src, dp.depth_cloud(np.zeros_like(db), k, 1.5, 0.004), np.eye(4), 0.03) is None


def test_numpy_and_open3d_icp_agree(monkeypatch):
    pytest.importorskip("open3d", exc_type=ImportError)
    k, da, db, truth = _moved_pair()
    init = truth.copy()
    init[:3, 3] += [0.004, -0.002, 0.002]                                # an odometry a few mm off
    out = {}
    for backend in ("numpy", "open3d"):
        _use(monkeypatch, backend)
        src, dst = (dp.depth_cloud(d, k, dp.REFERENCE_DEPTH_M, dp.VOXEL_M) for d in (da, db))
        out[backend] = dp.register(src, dst, init, dp.MAX_DIST_M)
    (t_np, fit_np), (t_o3d, fit_o3d) = out["numpy"], out["open3d"]
    assert np.linalg.norm(t_np[:3, 3] - t_o3d[:3, 3]) < 1e-3 and rotation_angle_deg(t_np[:3, :3], t_o3d[:3, :3]) < 0.05
    assert fit_np > 0.9 and fit_o3d > 0.9
    assert np.linalg.norm(t_np[:3, 3] - truth[:3, 3]) < 1e-3


def test_odometry_scale_is_the_same_with_numpy_and_open3d_icp(monkeypatch):
    pytest.importorskip("open3d", exc_type=ImportError)
    xs = np.arange(32) * 0.012
    k = np.array([60.0, 60.0, 40.0, 30.0])
    depths, intr, odo = _depths(xs, k), np.tile(k, (len(xs), 1)), _poses(xs * 1.05 + 0.3)
    est = {}
    for backend in ("numpy", "open3d"):
        _use(monkeypatch, backend)
        est[backend] = odometry_scale(depths, intr, odo)
    assert est["numpy"].note == est["open3d"].note == ""
    assert abs(est["numpy"].scale - est["open3d"].scale) < 0.005


def test_odometry_scale_recovers_a_stretched_odometry_and_stretch_undoes_it(icp):
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


def test_icp_trajectory_recovers_the_shape_of_a_drifting_odometry_in_its_frame(icp):
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
    with pytest.raises(ValueError, match="modes"):
        depth_initial_poses("lidar", depths, intr, odo)


def test_unproject_without_a_pose_gives_the_camera_frame_points_of_the_identity_pose():
    from nerf.surfaces import unproject

    rng = np.random.default_rng(5)
    depth = rng.uniform(0.2, 3.0, (12, 16))
    v, u = np.nonzero(depth > 1.0)
    k = np.array([20.0, 21.0, 8.2, 5.9])
    cam = unproject(depth, k, None, v, u)
    np.testing.assert_array_equal(cam, unproject(depth, k, np.eye(4), v, u))
    np.testing.assert_allclose(cam[:, 2], depth[v, u])
    np.testing.assert_allclose(cam[:, 0], (u + 0.5 - k[2]) / k[0] * depth[v, u])
