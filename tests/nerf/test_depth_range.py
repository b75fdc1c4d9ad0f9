"""What a window takes from its sensor depth: the far plane, ICP's depth limit and reach, the occupancy the
sensor saw through, and whether ICP's trajectory or the odometry's agrees better with the depth."""
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from nerf.config import NerfConfig, preset
from nerf.depth_poses import depth_initial_poses, icp_depth_limit_m
from nerf.model import init_occupancy
from nerf.occupancy import OccupancyGrid
from nerf.trainer import shift_weight, with_far_plane
from nerf.window import FALLBACK_FAR_M, MIN_PARALLAX_PER_M, depth_far_m, parallax_spread


def depth_frames(near_m: float, far_m: float, n: int = 4, shape=(60, 80), seed: int = 0) -> np.ndarray:
    """[n, H, W] depth uniformly between near_m and far_m, with a tenth of the pixels missing (0)."""
    rng = np.random.default_rng(seed)
    d = rng.uniform(near_m, far_m, (n, *shape)).astype(np.float32)
    d[rng.random(d.shape) < 0.1] = 0
    return d


def test_far_plane_covers_the_depth_and_is_stable_across_windows():
    row = depth_frames(0.45, 3.05)                  # a glasshouse row: near row at 0.45 m, wall at 3 m
    room = depth_frames(1.4, 6.0)                   # an office: nearest surfaces at 1.4 m, far wall at 6 m
    assert depth_far_m(row) == 3.5 and depth_far_m(depth_frames(0.45, 3.05, seed=1)) == 3.5
    assert depth_far_m(room) == 7.0
    assert depth_far_m(np.zeros((2, 8, 8), np.float32)) == FALLBACK_FAR_M
    # the fit takes it when far_m is 0 (the default) and keeps a value that is set
    assert NerfConfig().far_m == 0
    assert with_far_plane(preset("cpu"), room).far_m == 7.0
    assert with_far_plane(preset("cpu", far_m=2.0), room).far_m == 2.0
    with pytest.raises(ValueError, match="far_m"):
        NerfConfig(far_m=0.1)                       # nearer than the near plane


def two_planes(near_m: float, far_m: float, near_share: float, shape=(40, 50)) -> np.ndarray:
    """[2, H, W] depth: the first near_share of each image's rows at near_m, the rest at far_m, one pixel in
    ten missing."""
    d = np.full((2, *shape), far_m, np.float32)
    d[:, : int(round(near_share * shape[0]))] = near_m
    d[:, ::10, ::10] = 0
    return d


def test_parallax_spread_is_the_range_of_inverse_depth():
    # plants at 0.5 m in front of a far row at 2 m: 1/0.5 - 1/2 = 1.5 per metre, whatever the depths' shares
    assert parallax_spread(two_planes(0.5, 2.0, 0.5)) == pytest.approx(1.5)
    assert parallax_spread(two_planes(0.5, 2.0, 0.3)) == pytest.approx(1.5)
    # an office whose walls are 2-4 m away: 0.25 per metre; the same scene twice as far: half the spread
    assert parallax_spread(two_planes(2.0, 4.0, 0.5)) == pytest.approx(0.25)
    assert parallax_spread(two_planes(4.0, 8.0, 0.5)) == pytest.approx(0.125)
    # a few flying pixels (under the 10th percentile) do not set it
    d = two_planes(2.0, 4.0, 0.5)
    d[:, 0, :3] = 0.05
    assert parallax_spread(d) == pytest.approx(0.25)
    # one flat wall: no parallax, floored; no valid depth: unknown
    assert parallax_spread(np.full((2, 8, 8), 3.0, np.float32)) == MIN_PARALLAX_PER_M
    assert np.isnan(parallax_spread(np.zeros((2, 8, 8), np.float32)))


def test_shift_weight_grows_as_the_parallax_shrinks():
    cfg = preset("cpu", pose_shift_penalty=10.0)
    assert shift_weight(cfg, two_planes(0.5, 2.0, 0.5)) == pytest.approx(10 / 1.5 ** 2)
    assert shift_weight(cfg, two_planes(2.0, 4.0, 0.5)) == pytest.approx(10 / 0.25 ** 2)
    assert shift_weight(cfg, np.zeros((2, 8, 8), np.float32)) == 10.0      # no depth: the weight as set
    assert shift_weight(preset("cpu", pose_shift_penalty=0.0), two_planes(2.0, 4.0, 0.5)) == 0.0


def test_icp_depth_limit_follows_the_nearest_surfaces():
    assert icp_depth_limit_m(depth_frames(0.45, 3.05)) == 1.5
    assert icp_depth_limit_m(depth_frames(1.4, 6.0)) == 4.5     # 2.5 x 1.63 m, rounded up
    assert icp_depth_limit_m(depth_frames(1.4, 6.0), far_m=3.0) == 3.0


def wall_frames(invalid_second: bool):
    """Two cameras at the origin looking along +z at a wall 2 m away; the second has no depth at all."""
    h, w = 24, 32
    depths = torch.full((2, h, w), 2.0)
    if invalid_second:
        depths[1] = 0
    k = torch.tensor([[30.0, 30.0, w / 2, h / 2]] * 2)
    c2w = torch.eye(4).repeat(2, 1, 1)
    return depths, c2w, k


def occupancy_after_init(depths, c2w, k) -> OccupancyGrid:
    grid = OccupancyGrid(torch.tensor([-1.5, -1.5, 0.0]), torch.tensor([1.5, 1.5, 3.0]), 60)
    model = SimpleNamespace(cfg=preset("cpu", far_m=3.0), grid=grid)
    init_occupancy(model, depths, c2w, k, stride=1, carve_stride=1)
    return grid


def test_space_another_ray_saw_through_is_not_occupied_by_rays_without_depth():
    grid = occupancy_after_init(*wall_frames(invalid_second=True))
    axis = torch.stack([torch.zeros(50), torch.zeros(50), torch.linspace(0.3, 2.9, 50)], -1)
    occ = grid.query(axis)
    in_front, behind = axis[:, 2] < 1.6, axis[:, 2] > 2.2
    # the first camera saw through everything in front of the wall: empty, though the second saw nothing
    assert not occ[in_front].any()
    # nothing saw behind the wall: the second camera's rays keep it occupied there
    assert occ[behind].all()
    # the wall itself is occupied
    assert grid.query(torch.tensor([[0.0, 0.0, 2.0]])).all()


def test_without_any_valid_ray_the_whole_frustum_stays_occupied():
    depths, c2w, k = wall_frames(invalid_second=True)
    depths[0] = 0
    grid = occupancy_after_init(depths, c2w, k)
    axis = torch.stack([torch.zeros(20), torch.zeros(20), torch.linspace(0.3, 2.9, 20)], -1)
    assert grid.query(axis).all()


def corner_depths(positions: np.ndarray, h: int = 48, w: int = 64, f: float = 50.0):
    """Depth [N, H, W] of a room corner (wall z = 2, side wall x = 0.5, floor y = 0.4; OpenCV camera axes)
    seen by cameras at `positions` [N, 3] with identity rotation, and their intrinsics [N, 4]."""
    u, v = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    dx, dy = (u - w / 2) / f, (v - h / 2) / f
    out = []
    for p in positions:
        t = np.full((h, w), 2.0 - p[2])
        with np.errstate(divide="ignore", invalid="ignore"):
            for plane, dirs, at in ((0.5, dx, p[0]), (0.4, dy, p[1])):
                hit = np.where(dirs > 0, (plane - at) / dirs, np.inf)
                t = np.minimum(t, hit)
        out.append(t.astype(np.float32))
    return np.stack(out), np.array([[f, f, w / 2, h / 2]] * len(positions))


def poses_at(positions: np.ndarray) -> np.ndarray:
    c2w = np.tile(np.eye(4), (len(positions), 1, 1))
    c2w[:, :3, 3] = positions
    return c2w


@pytest.mark.parametrize("odometry_right", [True, False])
def test_icp_chain_is_taken_only_where_it_agrees_better_with_the_depth(monkeypatch, odometry_right):
    """ICP's links are replaced by links 8 mm off the truth (odometry right) or by the truth (odometry
    drifting 8 mm per frame): the chain is taken in the second case only."""
    import nerf.depth_poses as dp

    n = 12
    truth = np.stack([np.arange(n) * 0.02, np.zeros(n), np.zeros(n)], 1)
    depths, k = corner_depths(truth)
    drift = np.stack([np.arange(n) * 0.008, np.zeros(n), np.zeros(n)], 1)
    odometry = poses_at(truth if odometry_right else truth + drift)
    links = poses_at(truth + drift if odometry_right else truth)
    calls = iter(range(n - 1))

    def fake_register(src, dst, init, max_dist_m, min_points=100):
        i = next(calls)
        return np.linalg.inv(links[i + 1]) @ links[i], 1.0

    monkeypatch.setattr(dp, "register", fake_register)
    poses, info = depth_initial_poses("icp", depths, k, odometry)
    if odometry_right:
        assert info["depth_pose_votes"] == 0 and "odometry kept" in info["depth_pose_note"]
        assert np.allclose(poses, odometry)
    else:
        assert info["depth_pose_votes"] == n - 1
        steps = np.diff(poses[:, :3, 3], axis=0)
        assert np.allclose(steps, np.diff(truth, axis=0), atol=1e-6)   # the chain's shape is the truth's
