"""3D instance completion over a window's rendered frames (nerf/panoptic/complete.py), on ray-cast spheres."""
from dataclasses import replace

import numpy as np
import pytest

from nerf.config import PanopticConfig
from nerf.panoptic.complete import claims, complete_instances, rays_through_core, sphere_boxes
from nerf.surfaces import unproject


def _sphere_view(centre: np.ndarray, radius: float, cam_x: float, h: int = 40, w: int = 60
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Depth [H, W] of a sphere (background wall at z = 2 m) seen by a camera at (cam_x, 0, 0) looking
    along +z, the sphere mask, and the camera's c2w."""
    k = np.array([50.0, 50.0, w / 2, h / 2])
    v, u = np.mgrid[0:h, 0:w]
    d = np.stack([(u + 0.5 - k[2]) / k[0], (v + 0.5 - k[3]) / k[1], np.ones((h, w))], -1)   # z = 1 rays
    o = np.array([cam_x, 0.0, 0.0])
    oc = o - centre
    a, b, c = (d * d).sum(-1), 2 * (d * oc).sum(-1), oc @ oc - radius ** 2
    disc = b * b - 4 * a * c
    t = np.where(disc > 0, (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a), np.inf)
    hit = np.isfinite(t)
    depth = np.where(hit, t, 2.0)                                   # z-depth (rays have z = 1)
    c2w = np.eye(4)
    c2w[0, 3] = cam_x
    return depth, hit, c2w


def test_complete_instances_gives_a_fruit_its_stuff_labelled_side_but_not_the_leaf_in_front():
    centre, radius = np.array([0.0, 0.0, 0.5]), 0.04
    frames, poses = [], []
    for cam_x in (-0.02, 0.0, 0.02):
        depth, hit, c2w = _sphere_view(centre, radius, cam_x)
        sem = np.where(hit, 2, 1).astype(np.uint8)
        inst = np.where(hit, 7, 0).astype(np.int32)
        frames.append({"semantic": sem, "instance": inst, "depth": depth})
        poses.append(c2w)
    last = frames[-1]
    truth = last["instance"].copy()
    cols = np.arange(truth.shape[1])[None, :].repeat(truth.shape[0], 0)
    stuffed = (truth == 7) & (cols >= 30)                           # the head called half the fruit plant
    last["instance"][stuffed], last["semantic"][stuffed] = 0, 1
    leaf = (truth == 7) & (cols < 30) & (np.arange(truth.shape[0])[:, None] == 20)
    last["depth"][leaf] = 0.3                                      # a leaf 15 cm in front of the fruit
    last["instance"][leaf], last["semantic"][leaf] = 0, 1
    other = (truth == 0) & (cols == 0)
    last["instance"][other] = 9                                    # another instance's pixels stay its own
    k = np.array([[50.0, 50.0, 30.0, 20.0]] * 3)
    cfg = PanopticConfig(complete_margin_m=0.005, complete_min_points=50)
    added = complete_instances(frames, k, np.stack(poses), cfg)
    assert added == int(stuffed.sum())
    assert (last["instance"][stuffed] == 7).all() and (last["semantic"][stuffed] == 2).all()
    assert (last["instance"][leaf] == 0).all() and (last["instance"][other] == 9).all()
    assert (last["instance"][(truth == 0) & ~other] == 0).all()     # the wall behind stays stuff
    off = [dict(f, instance=f["instance"].copy()) for f in frames]
    assert complete_instances(off, k, np.stack(poses), PanopticConfig(instances=False)) == 0


def test_completion_by_ray_takes_a_rim_whose_depth_fell_behind_but_not_the_wall_around_the_fruit():
    centre, radius = np.array([0.0, 0.0, 0.5]), 0.04
    frames, poses = [], []
    for cam_x in (-0.02, 0.0, 0.02):
        depth, hit, c2w = _sphere_view(centre, radius, cam_x)
        frames.append({"semantic": np.where(hit, 2, 1).astype(np.uint8), "instance": np.where(hit, 7, 0).astype(np.int32),
                       "depth": depth})
        poses.append(c2w)
    k = np.array([[50.0, 50.0, 30.0, 20.0]] * 3)
    last, c2w = frames[-1], poses[-1]
    truth = last["instance"].copy()
    v, u = np.nonzero(truth == 7)
    _, closest = rays_through_core(last["depth"], k[2], c2w, v, u, centre[None], np.array([radius]), 0.0)
    core = np.zeros_like(truth, bool)
    core[v, u] = closest[:, 0] <= 0.7 * radius
    rim = (truth == 7) & ~core
    # the head called the fruit's right half stuff, and there the rendered depth slid to the wall behind
    cols = np.arange(truth.shape[1])[None, :].repeat(truth.shape[0], 0)
    lost = (truth == 7) & (cols >= 28)
    last["instance"][lost], last["semantic"][lost], last["depth"][lost] = 0, 1, 2.0
    leaf = lost & (np.arange(truth.shape[0])[:, None] == 20)
    last["depth"][leaf] = 0.3                                      # a leaf in front of the fruit stays a leaf
    cfg = PanopticConfig(complete_margin_m=0.005, complete_min_points=50, complete_core=0.7)
    off = [dict(f, instance=f["instance"].copy(), semantic=f["semantic"].copy()) for f in frames]
    assert complete_instances(off, k, np.stack(poses), replace(cfg, complete_core=0.0)) == 0   # depth test only
    added = complete_instances(frames, k, np.stack(poses), cfg)
    taken = lost & core & ~leaf
    assert added == int(taken.sum()) > 0
    assert (last["instance"][taken] == 7).all() and (last["semantic"][taken] == 2).all()
    assert (last["instance"][lost & rim] == 0).all() and (last["instance"][leaf] == 0).all()
    assert (last["instance"][truth == 0] == 0).all()                # the wall around the fruit stays stuff


def test_sphere_boxes_hold_every_pixel_whose_ray_meets_their_ball():
    rng = np.random.default_rng(3)
    h, w = 60, 80
    k = np.array([60.0, 55.0, 41.0, 28.0])
    ang = 0.3
    c2w = np.eye(4)
    c2w[:3, :3] = [[np.cos(ang), 0, np.sin(ang)], [0, 1, 0], [-np.sin(ang), 0, np.cos(ang)]]
    c2w[:3, 3] = [0.1, -0.05, 0.2]
    centres = c2w[:3, 3] + rng.uniform([-0.4, -0.3, 0.3], [0.4, 0.3, 1.0], (5, 3)) @ c2w[:3, :3].T
    radii = rng.uniform(0.02, 0.06, 5)
    v, u = np.mgrid[0:h, 0:w]
    d = np.stack([(u + 0.5 - k[2]) / k[0], (v + 0.5 - k[3]) / k[1], np.ones((h, w))], -1) @ c2w[:3, :3].T
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    oc = centres - c2w[:3, 3]                                       # [S, 3]
    along = d @ oc.T                                                # [H, W, S]
    meets = ((oc ** 2).sum(1) - along ** 2 <= radii ** 2) & (along > 0)
    boxes = sphere_boxes((h, w), k, c2w, centres, radii)
    for j, (v0, v1, u0, u1) in enumerate(boxes):
        inside = np.zeros((h, w), bool)
        inside[v0:v1, u0:u1] = True
        assert meets[..., j].any() and inside[meets[..., j]].all()  # conservative: no meeting pixel is lost
        assert inside.mean() < 0.3                                  # and most of the image is skipped
    behind = sphere_boxes((h, w), k, c2w, c2w[:3, 3][None] + 0.01, np.array([0.05]))
    assert behind == [None]                                         # a ball around the camera: any pixel


def _claims_of_every_pair(depth, free, k, c2w, centres, radii, cfg):
    """claims as every pixel tested against every sphere (the formulation claims must equal)."""
    v, u = np.nonzero(free & (depth > 0))
    rel = np.linalg.norm(unproject(depth, k, c2w, v, u)[:, None] - centres[None], axis=2)
    inside = rel <= radii + cfg.complete_margin_m
    score = np.where(inside, rel / radii, np.inf)
    if cfg.complete_core > 0:
        through, closest = rays_through_core(depth, k, c2w, v, u, centres, radii * cfg.complete_core,
                                             cfg.complete_margin_m)
        inside |= through
        score = np.minimum(score, np.where(through, closest / radii, np.inf))
    out = np.full(depth.shape, -1)
    hit = inside.any(1)
    out[v[hit], u[hit]] = score.argmin(1)[hit]
    return out


@pytest.mark.parametrize("core", [0.0, 0.7])
def test_claims_test_each_sphere_in_its_box_and_agree_with_every_pixel_against_every_sphere(core):
    rng = np.random.default_rng(5)
    h, w = 48, 64
    k = np.array([50.0, 50.0, 32.0, 24.0])
    c2w = np.eye(4)
    c2w[:3, 3] = [0.02, -0.01, 0.0]
    centres = np.c_[rng.uniform(-0.15, 0.15, 7), rng.uniform(-0.1, 0.1, 7), rng.uniform(0.45, 0.6, 7)]
    radii = rng.uniform(0.03, 0.06, 7)
    centres[-1], radii[-1] = [0.03, 0.0, 0.02], 0.04               # a ball reaching behind the camera
    depth = 0.52 + rng.normal(0.0, 0.04, (h, w))                    # a noisy surface through the fruits
    depth[rng.random((h, w)) < 0.05] = 0.0                          # no depth
    free = rng.random((h, w)) < 0.8                                 # stuff pixels
    cfg = PanopticConfig(complete_margin_m=0.005, complete_core=core)
    who = claims(depth, free, k, c2w, centres, radii, cfg)
    assert (who >= 0).sum() > 100 and len(np.unique(who[who >= 0])) >= 5
    assert (who[~free | (depth == 0)] == -1).all()
    np.testing.assert_array_equal(who, _claims_of_every_pair(depth, free, k, c2w, centres, radii, cfg))
