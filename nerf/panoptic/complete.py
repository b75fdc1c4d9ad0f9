"""3D instance completion over a window's rendered panoptic frames: each instance whose pixels, un-projected
with the rendered depth, fit a plausible fruit sphere claims the stuff pixels of every frame that lie inside
it (or whose ray passes through its core)."""
from __future__ import annotations

from collections.abc import Iterable

import numpy as np
from torch import Tensor

from nerf.config import PanopticConfig
from nerf.surfaces import fruit_sphere, unproject


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
        for sl_id in np.unique(inst[inst > 0]):
            v, u = np.nonzero((inst == sl_id) & (depth > 0))
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
    reach = radii + cfg.complete_margin_m     # nothing outside this ball around a centre is claimed
    added = 0
    for f, k, pose in zip(frames, intrinsics, c2w):
        depth = metres(f)
        v, u = np.nonzero((f["instance"] == 0) & (depth > 0) & near_spheres(depth.shape, k, pose, centres, reach))
        if not len(v):
            continue
        p = unproject(depth, k, pose, v, u)                             # [P, 3]
        rel = np.linalg.norm(p[:, None] - centres[None], axis=2)        # [P, S]
        inside = rel <= radii + cfg.complete_margin_m
        score = np.where(inside, rel / radii, np.inf)
        if cfg.complete_core > 0:
            through, closest = rays_through_core(depth, k, pose, v, u, centres, radii * cfg.complete_core,
                                                 cfg.complete_margin_m)
            inside |= through
            score = np.minimum(score, np.where(through, closest / radii, np.inf))
        hit = inside.any(1)
        if not hit.any():
            continue
        best = score.argmin(1)
        vv, uu, who = v[hit], u[hit], ids[best[hit]]
        f["instance"][vv, uu] = who
        f["semantic"][vv, uu] = [klass[int(i)] for i in who]
        added += int(hit.sum())
    return added


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


def near_spheres(hw: tuple[int, int], k: np.ndarray, c2w: np.ndarray, centres: np.ndarray,
                 radii: np.ndarray) -> np.ndarray:
    """[H, W] bool: the pixels whose ray can meet one of the balls (centres [S, 3], radii [S]) in front of the
    camera: the union of their sphere_boxes (the whole image for a ball that reaches behind the camera). A
    point of a ball in front of the camera projects inside its box, so the pixels outside every box can be
    skipped without changing any result."""
    mask = np.zeros(hw, bool)
    for box in sphere_boxes(hw, k, c2w, centres, radii):
        if box is None:
            return np.ones(hw, bool)
        v0, v1, u0, u1 = box
        if u0 < u1 and v0 < v1:
            mask[v0:v1, u0:u1] = True
    return mask


def rays_through_core(depth: np.ndarray, k: np.ndarray, c2w: np.ndarray, v: np.ndarray, u: np.ndarray,
                      centres: np.ndarray, core_radii: np.ndarray, margin_m: float) -> tuple[np.ndarray, np.ndarray]:
    """For pixels (v, u) of a frame with rendered z-depth `depth`, intrinsics k = (fx, fy, cx, cy) and pose
    c2w, and spheres (centres [S, 3], core_radii [S]): ([P, S] bool: the pixel's ray passes within the
    sphere in front of the camera and its rendered depth is not in front of the ray's entry into it by more
    than margin_m, [P, S] the ray's closest distance to each centre)."""
    d = unproject(np.ones_like(depth), k, c2w, v, u) - c2w[:3, 3]      # world rays with camera z = 1
    norm = np.linalg.norm(d, axis=1)                                    # ray length per unit of z-depth
    oc = centres - c2w[:3, 3]                                           # [S, 3]
    along = (d / norm[:, None]) @ oc.T                                  # [P, S] ray length to the closest point
    dist2 = np.maximum((oc ** 2).sum(1)[None] - along ** 2, 0.0)
    entry_z = (along - np.sqrt(np.maximum(core_radii[None] ** 2 - dist2, 0.0))) / norm[:, None]
    through = (dist2 <= core_radii[None] ** 2) & (along > 0) & (depth[v, u][:, None] >= entry_z - margin_m)
    return through, np.sqrt(dist2)
