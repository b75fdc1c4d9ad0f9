"""Exact ray casting of the row: colour (view-independent shading), z-depth and ground-truth labels.

Pixel (i, j) of a W x H image looks along K^-1 (j + 0.5, i + 0.5, 1) in the OpenCV optical frame
(x right, y down, z forward), i.e. pixel centres sit at half-integer coordinates, as in the NeRF
code. Depth is the z coordinate in that frame (what a RealSense reports), not the ray length.

Shading is Lambert with one fixed light plus ambient, times an albedo from 3D procedural textures
at the hit point and a canopy-depth darkening (a cheap, view-independent stand-in for ambient
occlusion): no specular term, so every view of a surface point has the same colour.
"""
from __future__ import annotations

import numpy as np

from synthetic import scene as S
from synthetic.textures import fbm, smoothstep, value_noise

LIGHT = np.array([0.25, -0.55, 0.8], np.float32) / np.float32(np.linalg.norm([0.25, -0.55, 0.8]))
AMBIENT, DIFFUSE = 0.42, 0.62
SKY_RGB = np.array([0.86, 0.89, 0.92], np.float32)
RIPENESS_RGB = {S.GREEN: (0.10, 0.29, 0.05), S.RED: (0.60, 0.04, 0.03)}
MIXED_FROM, MIXED_TO = np.array([0.22, 0.36, 0.05], np.float32), np.array([[0.90, 0.66, 0.05], [0.90, 0.40, 0.03]],
                                                                           np.float32)


def camera_rays(k: np.ndarray, width: int, height: int, supersample: int) -> np.ndarray:
    """[N, 3] float32 ray directions (z = 1) in the camera frame: first the H * W pixel centres
    (row-major), then the colour-only anti-aliasing samples: none for supersample 1; for 2 the
    (H + 1) x (W + 1) pixel corners, shared by neighbouring pixels (quincunx: about 2 rays per pixel);
    for s >= 3 an s x s grid inside every pixel, laid out as [H, s, W, s]."""
    def grid(u: np.ndarray, v: np.ndarray) -> np.ndarray:
        uu, vv = np.meshgrid(u, v)
        return np.stack([(uu - k[0, 2]) / k[0, 0], (vv - k[1, 2]) / k[1, 1], np.ones_like(uu)], -1).reshape(-1, 3)

    parts = [grid(np.arange(width) + 0.5, np.arange(height) + 0.5)]
    if supersample == 2:
        parts.append(grid(np.arange(width + 1.0), np.arange(height + 1.0)))
    elif supersample >= 3:
        s = supersample
        parts.append(grid((np.arange(width * s) + 0.5) / s, (np.arange(height * s) + 0.5) / s))
    return np.concatenate(parts).astype(np.float32)


def resolve_colour(rgb: np.ndarray, width: int, height: int, supersample: int) -> np.ndarray:
    """Colours of the camera_rays() samples [N, 3] -> pixel colours [H, W, 3]: the centre alone (1),
    1/2 centre + 1/8 of each corner (2), the mean of the s x s grid (s >= 3)."""
    n = width * height
    centre = rgb[:n].reshape(height, width, 3)
    if supersample == 1:
        return centre
    if supersample == 2:
        c = rgb[n:].reshape(height + 1, width + 1, 3)
        return 0.5 * centre + 0.125 * (c[:-1, :-1] + c[:-1, 1:] + c[1:, :-1] + c[1:, 1:])
    s = supersample
    return rgb[n:].reshape(height, s, width, s, 3).mean((1, 3))


def _cast(scene: S.Scene, c2w: np.ndarray, dirs_cam: np.ndarray, nthreads: int) -> dict[str, np.ndarray]:
    d = dirs_cam @ c2w[:3, :3].T.astype(np.float32)
    rays = np.empty((len(d), 6), np.float32)
    rays[:, :3] = c2w[:3, 3]
    rays[:, 3:] = d
    import open3d as o3d  # here, not at the top: the model stages import this module and must run without Open3D

    hit = scene.raycaster.cast_rays(o3d.core.Tensor.from_numpy(rays), nthreads=nthreads)
    t = hit["t_hit"].numpy()
    return {"t": t, "ok": np.isfinite(t), "prim": hit["primitive_ids"].numpy(), "uv": hit["primitive_uvs"].numpy(),
            "origin": c2w[:3, 3].astype(np.float32), "dir": d}


def _local(scene: S.Scene, part: np.ndarray, p: np.ndarray) -> np.ndarray:
    """World points -> the part's own frame: R^T (p - o)."""
    return np.einsum("nij,ni->nj", scene.rot[part], p - scene.origin[part])


def albedo(scene: S.Scene, p: np.ndarray, part: np.ndarray, texture_scale: float = 1.0) -> np.ndarray:
    """[N, 3] float32 albedo in [0, 1] of world points p [N, 3] on parts `part` [N]."""
    seed, ts = scene.seed, texture_scale
    mat = scene.material[part]
    # points sorted by material (a stable radix sort of small ints): each material's points are one slice
    order = np.argsort(mat, kind="stable")
    counts = np.bincount(mat, minlength=len(S.MATERIALS))
    ends = np.cumsum(counts)
    p_by, part_by = p[order], part[order]
    param_by = scene.param[part_by]
    a_by = np.empty((len(p), 3), np.float32)
    for m in np.flatnonzero(counts):
        sel = slice(ends[m] - counts[m], ends[m])
        q, pr, prm = p_by[sel], part_by[sel], param_by[sel]
        if m == S.LEAF:
            loc = _local(scene, pr, q)
            tone = 0.55 * prm[:, 0] + 0.45 * fbm(q, 0.035 * ts, 2, seed + 1)
            base = np.array([0.07, 0.22, 0.05], np.float32) + np.outer(tone, [0.12, 0.22, 0.06]).astype(np.float32)
            ax, ay, length = loc[:, 0], np.abs(loc[:, 1]), prm[:, 1]
            midrib = smoothstep(0.0035, 0.0012, ay) * (ax < 0.9 * length)
            spacing = length / 7
            sv = (ax - 0.9 * ay) / spacing
            lateral = smoothstep(0.0022, 0.0007, np.abs(sv - np.round(sv)) * spacing) * (ay > 0.002) * (sv > 0.6)
            lateral *= smoothstep(0.5, 0.35, ay / np.maximum(prm[:, 2], 1e-3))
            vein = np.maximum(midrib, 0.7 * lateral)
            fine = 0.88 + 0.24 * value_noise(q, 0.004 * ts, seed + 2)
            a = base * fine[:, None]
            a = a + vein[:, None] * (np.array([0.16, 0.22, 0.08], np.float32) - 0.4 * a)
        elif m == S.STEM:
            streak = value_noise(q * np.array([1.0, 1.0, 0.15], np.float32), 0.002 * ts, seed + 3)
            a = np.array([0.26, 0.42, 0.14], np.float32) * (0.75 + 0.2 * fbm(q, 0.03 * ts, 2, seed + 4)
                                                             + 0.2 * streak)[:, None]
        elif m == S.FRUIT:
            a = _fruit_albedo(scene, q, pr, prm, ts)
        elif m == S.FLOOR:
            dirt = smoothstep(0.55, 0.75, fbm(q, 0.12 * ts, 3, seed + 5))
            a = np.array([0.80, 0.80, 0.76], np.float32) * (0.8 + 0.2 * fbm(q, 0.5 * ts, 2, seed + 6))[:, None]
            a = a + dirt[:, None] * (np.array([0.42, 0.35, 0.27], np.float32) - a)
            a *= (0.85 + 0.3 * value_noise(q, 0.006 * ts, seed + 7))[:, None]
        elif m == S.WALL:
            frame_x = np.abs(((q[:, 0] + 0.02) % 1.25) - 0.02) < 0.02
            frame_z = np.abs(((q[:, 2] + 0.02) % 0.9) - 0.02) < 0.02
            a = np.array([0.70, 0.74, 0.72], np.float32) * (0.7 + 0.3 * fbm(q, 0.3 * ts, 3, seed + 8))[:, None]
            a[frame_x | frame_z] = np.array([0.50, 0.51, 0.53], np.float32)
            a *= (0.9 + 0.2 * value_noise(q, 0.012 * ts, seed + 9))[:, None]
        elif m == S.PIPE:
            a = np.array([0.82, 0.82, 0.80], np.float32) * (0.85 + 0.15 * fbm(q, 0.05 * ts, 2, seed + 10))[:, None]
            rust = value_noise(q, 0.01 * ts, seed + 11) > 0.8
            a[rust] *= np.array([0.8, 0.6, 0.45], np.float32)
        else:  # POST
            a = np.array([0.58, 0.60, 0.62], np.float32) * (0.8 + 0.3 * fbm(q, 0.05 * ts, 3, seed + 12))[:, None]
        a_by[sel] = a
    out = np.empty_like(a_by)
    out[order] = a_by
    return np.clip(out, 0.0, 1.0, out=out)


def _fruit_albedo(scene: S.Scene, q: np.ndarray, pr: np.ndarray, prm: np.ndarray, ts: float) -> np.ndarray:
    """Ripeness colour with patches, darker grooves between the lobes, lenticel specks and a green calyx."""
    seed = scene.seed
    klass = scene.klass[pr]
    loc = _local(scene, pr, q)
    hue, length, diam = prm[:, 0], prm[:, 1], prm[:, 2]
    n_lobes, phase = np.floor(prm[:, 3]), (prm[:, 3] % 1.0) * 2 * np.pi
    a = np.empty((len(q), 3), np.float32)
    for c, rgb in RIPENESS_RGB.items():
        a[klass == c] = rgb
    mixed = klass == S.MIXED
    if mixed.any():
        target = MIXED_TO[(hue[mixed] > 0.5).astype(int)]
        w = smoothstep(0.35, 0.65, fbm(q[mixed], 0.03 * ts, 2, seed + 13) + 0.3 * (hue[mixed] - 0.5))
        a[mixed] = MIXED_FROM + w[:, None] * (target - MIXED_FROM)
    a *= (0.9 + 0.2 * hue)[:, None]
    patch = fbm(q, 0.025 * ts, 2, seed + 14)
    a *= (0.78 + 0.4 * patch)[:, None]
    theta = np.arctan2(loc[:, 1], loc[:, 0])
    groove = (0.5 - 0.5 * np.cos(n_lobes * theta + phase)) ** 3
    a *= (1.0 - 0.3 * groove)[:, None]
    speck = value_noise(q, 0.0025 * ts, seed + 15) > 0.8
    a[speck] *= 0.8
    r_xy = np.hypot(loc[:, 0], loc[:, 1])
    calyx = (loc[:, 2] > 0.3 * length) & (r_xy < 0.22 * diam)
    a[calyx] = np.array([0.22, 0.32, 0.10], np.float32) * (0.8 + 0.4 * value_noise(q[calyx], 0.004 * ts, seed + 16)
                                                           )[:, None]
    return a


def shade(scene: S.Scene, p: np.ndarray, normal: np.ndarray, part: np.ndarray, texture_scale: float = 1.0
          ) -> np.ndarray:
    """[N, 3] float32 colour in [0, 1] at world points p with unit normals, on parts `part`."""
    a = albedo(scene, p, part, texture_scale)
    mat = scene.material[part]
    ndl = normal @ LIGHT
    thin = mat == S.LEAF  # leaves are lit from both sides (and a little translucent)
    lambert = np.where(thin, 0.85 * np.abs(ndl), np.maximum(ndl, 0.0))
    row_y = scene.param[part, 3]
    depth_in = np.where(np.isfinite(row_y), p[:, 1] - (row_y - 0.15), 0.0)
    ao = 1.0 - 0.45 * np.clip(depth_in / 0.35, 0.0, 1.0)  # deeper in the canopy = darker
    return np.clip(a * ((AMBIENT + DIFFUSE * lambert) * ao)[:, None], 0.0, 1.0)


def _smooth_normals(scene: S.Scene, prim: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Unit normals [N, 3] at the hits: the triangle's corner normals blended by the barycentric (u, v)."""
    cn = scene.corner_normals.take(prim, axis=0)  # [N, 3, 3]
    u, v = uv[:, 0:1], uv[:, 1:2]
    n = (1 - u - v) * cn[:, 0]
    n += u * cn[:, 1]
    n += v * cn[:, 2]
    sq = n * n
    length = np.sqrt(sq[:, 0] + sq[:, 1] + sq[:, 2])
    n /= np.maximum(length, 1e-8)[:, None]
    return n


def render(scene: S.Scene, c2w: np.ndarray, k: np.ndarray, width: int, height: int, supersample: int = 2,
           texture_scale: float = 1.0, nthreads: int = 1, rays: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """Ray-cast one camera (c2w: 4x4 camera-to-world, OpenCV optical frame).

    Returns rgb [H, W, 3] uint8 (anti-aliased as in camera_rays), and from the pixel-centre ray: depth
    [H, W] float32 metres (z in the camera frame, 0 = no hit), semantic [H, W] uint8 and instance
    [H, W] uint16 (fruit ids). `rays` is camera_rays(k, width, height, supersample), if cached."""
    if rays is None:
        rays = camera_rays(k, width, height, supersample)
    hit = _cast(scene, c2w, rays, nthreads)
    ok = hit["ok"]
    on = slice(None) if ok.all() else ok  # (an enclosed greenhouse: usually every ray hits, and no copy is needed)
    prim = hit["prim"][on].astype(np.int64)
    pts = hit["origin"] + hit["dir"][on] * hit["t"][on, None]
    part_hit = scene.part_of_triangle[prim]
    part = np.zeros(len(ok), part_hit.dtype)   # (0 where the ray hits nothing)
    part[on] = part_hit
    rgb = np.empty((len(ok), 3), np.float32)
    rgb[~ok] = SKY_RGB
    rgb[on] = shade(scene, pts, _smooth_normals(scene, prim, hit["uv"][on]), part_hit, texture_scale)
    colour = resolve_colour(rgb, width, height, supersample)
    n = width * height
    cok, part = ok[:n], part[:n]
    return {
        "rgb": np.round(colour * 255).astype(np.uint8),
        "depth": np.where(cok, hit["t"][:n], 0.0).astype(np.float32).reshape(height, width),
        "semantic": np.where(cok, scene.klass[part], S.BACKGROUND).astype(np.uint8).reshape(height, width),
        "instance": np.where(cok, scene.instance[part], 0).astype(np.uint16).reshape(height, width),
    }
