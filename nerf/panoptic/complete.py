"""3D instance completion over a window's rendered panoptic frames: each instance whose pixels, un-projected
with the rendered depth, fit a plausible fruit sphere claims the stuff pixels of every frame that lie inside
it (or whose ray passes through its core)."""
from __future__ import annotations

from collections.abc import Iterable

import numpy as np
from torch import Tensor

from nerf.config import PanopticConfig
from nerf.surfaces import fruit_sphere, runs_by_key, unproject


def instance_spheres(frames: Iterable[tuple[np.ndarray, np.ndarray]], intrinsics: np.ndarray, c2w: np.ndarray,
                     cfg: PanopticConfig, max_per_frame: int = 400) -> dict[int, tuple[np.ndarray, float]]:
    """{instance id: (sphere centre [3], radius)} of the instances of a window's rendered frames
    (`frames` = [(instance [H, W], depth [H, W] metres)], with `intrinsics` [N, 4] fx fy cx cy and `c2w`
    [N, 4, 4] per frame) whose pixels, un-projected with the depth, fit a plausible fruit sphere
    (nerf.surfaces.plausible_fit, radius <= cfg.complete_max_radius_m). A fruit seen only as a shallow cap
    gets none (tried: a sphere of half the cap's extent behind it claimed leaves and fixed no fruit)."""
    pts: dict[int, list[np.ndarray]] = {}
    rng = np.random.default_rng(0)
    for (inst, depth), k, pose in zip(frames, intrinsics, c2w):
        vs, us = np.nonzero((inst > 0) & (depth > 0))
        vs, us, slots, starts, ends = runs_by_key(vs, us, inst[vs, us])
        for sl_id, s0, s1 in zip(slots[starts], starts, ends):
            v, u = vs[s0:s1], us[s0:s1]
            if len(v) > max_per_frame:
                pick = rng.choice(len(v), max_per_frame, replace=False)
                v, u = v[pick], u[pick]
            pts.setdefault(int(sl_id), []).append(unproject(depth, k, pose, v, u))
    out = {}
    for sl_id, chunks in pts.items():
        p = np.concatenate(chunks)
        if len(p) < cfg.complete_min_points:
            continue
        fit = fruit_sphere(p, cfg.complete_max_radius_m)
        if fit is not None:
            out[sl_id] = fit[:2]
    return out


def complete_instances(frames: list[dict], intrinsics: np.ndarray, c2w: np.ndarray, cfg: PanopticConfig) -> int:
    """3D instance completion over a window's rendered frames (dicts with 'semantic' [H, W] uint8, 'instance'
    [H, W] int32, 'depth' [H, W] metres, numpy or torch; changed in place): every stuff pixel whose
    un-projected point lies inside an instance's sphere (instance_spheres, radius + cfg.complete_margin_m)
    joins that instance with its majority class; a pixel inside two spheres goes to the one it lies deeper
    in (smaller distance / radius). Pixels of other instances are never taken. Returns the pixels added
    (0 with cfg.complete_3d off)."""
    if not (cfg.complete_3d and cfg.instances and frames):
        return 0
    as_np = lambda a: a.detach().cpu().numpy() if isinstance(a, Tensor) else np.asarray(a)  # noqa: E731
    # float64 depth made frame by frame, in each pass: a window's at once would hold 280 MB at 1280x720
    metres = lambda f: as_np(f["depth"]).astype(np.float64)  # noqa: E731
    spheres = instance_spheres(((f["instance"], metres(f)) for f in frames), intrinsics, c2w, cfg)
    if not spheres:
        return 0
    klass = {}
    for sl_id in spheres:
        cls = np.concatenate([f["semantic"][f["instance"] == sl_id] for f in frames])
        vals, n = np.unique(cls, return_counts=True)
        klass[sl_id] = int(vals[np.argmax(n)])
    ids = np.array(list(spheres))
    centres = np.stack([spheres[i][0] for i in ids])                    # [S, 3]
    radii = np.array([spheres[i][1] for i in ids])                      # [S]
    added = 0
    for f, k, pose in zip(frames, intrinsics, c2w):
        depth = metres(f)
        who = claims(depth, f["instance"] == 0, k, pose, centres, radii, cfg)
        vv, uu = np.nonzero(who >= 0)
        if not len(vv):
            continue
        f["instance"][vv, uu] = ids[who[vv, uu]]
        f["semantic"][vv, uu] = [klass[int(i)] for i in ids[who[vv, uu]]]
        added += len(vv)
    return added


def claims(depth: np.ndarray, free: np.ndarray, k: np.ndarray, c2w: np.ndarray, centres: np.ndarray,
           radii: np.ndarray, cfg: PanopticConfig) -> np.ndarray:
    """[H, W] the index of the sphere (centres [S, 3], radii [S]) each `free` pixel with depth joins, -1 none:
    its point lies within radius + complete_margin_m of the centre, or (complete_core > 0) its ray passes
    through the sphere's core with the depth not in front of it; of several, the smallest distance / radius
    (the first sphere on a tie). Each sphere tests only the pixels of its image box (sphere_boxes), so a frame
    costs the spheres' boxes, not pixels x spheres."""
    h, w = depth.shape
    best, who = np.full((h, w), np.inf), np.full((h, w), -1)
    free = free & (depth > 0)
    for j, box in enumerate(sphere_boxes((h, w), k, c2w, centres, radii + cfg.complete_margin_m)):
        v0, v1, u0, u1 = (0, h, 0, w) if box is None else box
        v, u = np.nonzero(free[v0:v1, u0:u1])
        v, u = v + v0, u + u0
        if not len(v):
            continue
        rel = np.linalg.norm(unproject(depth, k, c2w, v, u) - centres[j], axis=1)
        score = np.where(rel <= radii[j] + cfg.complete_margin_m, rel / radii[j], np.inf)
        if cfg.complete_core > 0:
            through, closest = rays_through_core(depth, k, c2w, v, u, centres[j:j + 1],
                                                 radii[j:j + 1] * cfg.complete_core, cfg.complete_margin_m)
            score = np.minimum(score, np.where(through[:, 0], closest[:, 0] / radii[j], np.inf))
        better = score < best[v, u]
        best[v[better], u[better]] = score[better]
        who[v[better], u[better]] = j
    return who


def sphere_boxes(hw: tuple[int, int], k: np.ndarray, c2w: np.ndarray, centres: np.ndarray,
                 radii: np.ndarray) -> list[tuple[int, int, int, int] | None]:
    """Per ball (centres [S, 3], radii [S]): the image box (v0, v1, u0, u1), clipped to the image (empty where
    v0 >= v1 or u0 >= u1) that holds the projection of every point of the ball in front of the camera (the
    box of its bounding cube), or None for a cube that reaches behind the camera (any pixel)."""
    h, w = hw
    out: list[tuple[int, int, int, int] | None] = []
    cam = (centres - c2w[:3, 3]) @ c2w[:3, :3]                          # [S, 3] centres in the camera frame
    corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], np.float64)
    for c, r in zip(cam, radii):
        if c[2] - r <= 1e-6:
            out.append(None)
            continue
        q = c + corners * r                                             # [8, 3], all in front
        u = k[0] * q[:, 0] / q[:, 2] + k[2] - 0.5                       # pixel index of the projection
        v = k[1] * q[:, 1] / q[:, 2] + k[3] - 0.5
        out.append((max(0, int(np.floor(v.min())) - 1), min(h, int(np.ceil(v.max())) + 2),
                    max(0, int(np.floor(u.min())) - 1), min(w, int(np.ceil(u.max())) + 2)))
    return out


def rays_through_core(depth: np.ndarray, k: np.ndarray, c2w: np.ndarray, v: np.ndarray, u: np.ndarray,
                      centres: np.ndarray, core_radii: np.ndarray, margin_m: float) -> tuple[np.ndarray, np.ndarray]:
    """For pixels (v, u) of a frame with rendered z-depth `depth`, intrinsics k = (fx, fy, cx, cy) and pose
    c2w, and spheres (centres [S, 3], core_radii [S]): ([P, S] bool: the pixel's ray passes within the
    sphere in front of the camera and its rendered depth is not in front of the ray's entry into it by more
    than margin_m, [P, S] the ray's closest distance to each centre)."""
    d = unproject(np.broadcast_to(1.0, depth.shape), k, c2w, v, u) - c2w[:3, 3]   # world rays with camera z = 1
    norm = np.linalg.norm(d, axis=1)                                    # ray length per unit of z-depth
    oc = centres - c2w[:3, 3]                                           # [S, 3]
    along = (d / norm[:, None]) @ oc.T                                  # [P, S] ray length to the closest point
    dist2 = np.maximum((oc ** 2).sum(1)[None] - along ** 2, 0.0)
    entry_z = (along - np.sqrt(np.maximum(core_radii[None] ** 2 - dist2, 0.0))) / norm[:, None]
    through = (dist2 <= core_radii[None] ** 2) & (along > 0) & (depth[v, u][:, None] >= entry_z - margin_m)
    return through, np.sqrt(dist2)
