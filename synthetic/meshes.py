"""Triangle meshes of the row's parts, built in a local frame: boxes, tubes, leaf blades, peppers.

Every function returns a `Mesh` with per-vertex normals (smooth shading) in its own local frame; the
scene places it with a rotation and a translation and keeps that frame, so textures can use local
coordinates (a leaf's midrib, a pepper's lobes).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Mesh:
    vertices: np.ndarray
    """[V, 3] float32 metres."""
    triangles: np.ndarray
    """[T, 3] int32 vertex indices."""
    normals: np.ndarray
    """[V, 3] float32 unit vertex normals (or [T, 3, 3] per-corner normals for flat faces)."""

    def transformed(self, rot: np.ndarray, trans: np.ndarray) -> Mesh:
        """x -> rot @ x + trans."""
        r = np.asarray(rot, np.float32)
        return Mesh(self.vertices @ r.T + np.asarray(trans, np.float32), self.triangles, self.normals @ r.T)

    def corner_normals(self) -> np.ndarray:
        """[T, 3, 3] normal at each triangle corner."""
        return self.normals if self.normals.ndim == 3 else self.normals[self.triangles]


def rotation(axis: np.ndarray, angle_rad: float) -> np.ndarray:
    """Rodrigues: rotation by `angle_rad` about `axis` (3x3)."""
    a = np.asarray(axis, np.float64)
    a = a / np.linalg.norm(a)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(angle_rad) * k + (1 - np.cos(angle_rad)) * k @ k


def frame_from_z(z: np.ndarray, hint: np.ndarray = np.array([1.0, 0.0, 0.0])) -> np.ndarray:
    """A rotation whose third column is the unit vector along `z` (first column close to `hint`)."""
    z = np.asarray(z, np.float64) / np.linalg.norm(z)
    x = hint - (hint @ z) * z
    if np.linalg.norm(x) < 1e-6:
        x = np.array([0.0, 1.0, 0.0]) - z[1] * z
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z], 1)


def grid_triangles(n_u: int, n_v: int, wrap_u: bool) -> np.ndarray:
    """Triangles of an n_u x n_v vertex grid (index u * n_v + v); wrap_u closes the u direction."""
    idx = np.arange(n_u * n_v).reshape(n_u, n_v)
    if wrap_u:
        idx = np.concatenate([idx, idx[:1]], 0)
    a, b = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel()
    c, d = idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    return np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)]).astype(np.int32)


def vertex_normals(v: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Area-weighted vertex normals [V, 3] (orientation follows the triangle winding)."""
    fn = np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]])
    n = np.zeros_like(v, dtype=np.float64)
    for k in range(3):
        np.add.at(n, t[:, k], fn)
    length = np.linalg.norm(n, axis=1, keepdims=True)
    return (n / np.maximum(length, 1e-12)).astype(np.float32)


def _mesh(v: np.ndarray, t: np.ndarray) -> Mesh:
    v = np.asarray(v, np.float64)
    return Mesh(v.astype(np.float32), t.astype(np.int32), vertex_normals(v, t))


def box(lo: np.ndarray, hi: np.ndarray) -> Mesh:
    """Axis-aligned box with flat faces, normals pointing out."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    verts, tris, norms = [], [], []
    for axis in range(3):
        for side in (0, 1):
            n = np.zeros(3)
            n[axis] = 1.0 if side else -1.0
            u, w = [a for a in range(3) if a != axis]
            quad = []
            for du, dw in ((0, 0), (1, 0), (1, 1), (0, 1)):
                p = np.where(np.arange(3) == axis, (hi if side else lo)[axis], 0.0)
                p[u] = (lo, hi)[du][u]
                p[w] = (lo, hi)[dw][w]
                quad.append(p)
            base = len(verts)
            verts += quad
            tri = np.array([[0, 1, 2], [0, 2, 3]]) + base
            if (np.cross(quad[1] - quad[0], quad[2] - quad[0]) @ n) < 0:
                tri = tri[:, ::-1]
            tris.append(tri)
            norms.append(np.broadcast_to(n, (2, 3, 3)))
    return Mesh(np.array(verts, np.float32), np.concatenate(tris).astype(np.int32),
                np.concatenate(norms).astype(np.float32))


def tube(points: np.ndarray, radii: np.ndarray, res: int = 8) -> Mesh:
    """A generalised cylinder along a polyline [K, 3] with radius [K] (open ends), in world/local units."""
    pts = np.asarray(points, np.float64)
    radii = np.broadcast_to(np.asarray(radii, np.float64), (len(pts),))
    tang = np.gradient(pts, axis=0)
    tang /= np.linalg.norm(tang, axis=1, keepdims=True)
    ang = np.linspace(0, 2 * np.pi, res, endpoint=False)
    rings = []
    ref = np.array([1.0, 0.0, 0.0]) if abs(tang[0, 0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    for p, t, r in zip(pts, tang, radii):
        x = ref - (ref @ t) * t
        x /= np.linalg.norm(x)
        y = np.cross(t, x)
        ref = x  # parallel transport keeps the rings from twisting
        rings.append(p + r * (np.cos(ang)[:, None] * x + np.sin(ang)[:, None] * y))
    v = np.stack(rings, 1).reshape(-1, 3)  # index = ring angle * K + k
    return _mesh(v, grid_triangles(res, len(pts), wrap_u=True))


def leaf_blade(length_m: float, width_m: float, fold: float, droop: float, res: int = 7) -> Mesh:
    """An ovate pepper leaf in its local frame: midrib along +x from the petiole (x = 0) to the tip
    (x = length_m), width along y (widest at 40 % of the length, pointed tip), folded up along the
    midrib (`fold`: rise of the edges / half width) and drooping down towards the tip (`droop`: drop
    of the tip / length)."""
    s = np.linspace(0.0, 1.0, res + 1)
    c = np.linspace(-1.0, 1.0, res + 1)
    ss, cc = np.meshgrid(s, c, indexing="ij")
    # ovate outline: half width as a function of s, 0 at both ends, max at s = 0.4
    outline = np.sin(np.pi * np.clip(ss, 0, 1) ** 0.76) ** 0.9
    half_w = 0.5 * width_m * np.maximum(outline, 0.02)
    x = ss * length_m
    y = cc * half_w
    z = fold * np.abs(cc) ** 1.5 * half_w - droop * length_m * ss ** 2
    return _mesh(np.stack([x, y, z], -1).reshape(-1, 3), grid_triangles(res + 1, res + 1, wrap_u=False))


def pepper(diameter_m: float, length_m: float, n_lobes: int, phase: float, res: int = 20) -> Mesh:
    """A blocky sweet pepper in its local frame: axis along z, centre at the origin, top (stalk end)
    at z = +length_m / 2. Lobes bulge the sides and dimple the bottom; the shoulders are broad with a
    cup where the stalk joins. Returns a closed mesh with outward normals."""
    n_s, n_t = res, 2 * res
    s = np.linspace(0.0, 1.0, n_s + 1)[1:-1]  # bottom (0) to top (1); the poles are added below
    th = np.linspace(0, 2 * np.pi, n_t, endpoint=False)
    tt, ss = np.meshgrid(th, s, indexing="ij")  # [n_t, n_s - 1], vertex index = theta * (n_s - 1) + s
    lobe = np.cos(n_lobes * tt + phase)
    # super-ellipse profile: flat-ish sides (blocky), rounded shoulders and bottom
    e = 2 * ss - 1
    prof = (1 - np.abs(e) ** 3.2) ** (1 / 3.2)
    taper = 1 - 0.16 * (1 - ss)  # narrower bottom
    r = 0.5 * diameter_m * prof * taper * (1 + 0.07 * lobe)
    z = 0.5 * length_m * e
    # bottom dimples between the lobes, shoulder cup around the stalk
    z = z - 0.06 * length_m * (1 - lobe) * np.clip(-e, 0, 1) ** 4
    z = z - 0.12 * length_m * np.clip(e, 0, 1) ** 6 * (1 - np.clip(r / (0.5 * diameter_m), 0, 1))
    ring = np.stack([r * np.cos(tt), r * np.sin(tt), z], -1).reshape(-1, 3)
    bottom = [0.0, 0.0, -0.5 * length_m + 0.03 * length_m]
    top = [0.0, 0.0, 0.5 * length_m - 0.12 * length_m]
    v = np.concatenate([ring, [bottom, top]])
    tris = [grid_triangles(n_t, n_s - 1, wrap_u=True)]
    nb, ntop = len(ring), len(ring) + 1
    j = np.arange(n_t)
    jn = (j + 1) % n_t
    tris.append(np.stack([np.full(n_t, nb), jn * (n_s - 1), j * (n_s - 1)], 1))
    tris.append(np.stack([np.full(n_t, ntop), j * (n_s - 1) + n_s - 2, jn * (n_s - 1) + n_s - 2], 1))
    t = np.concatenate(tris).astype(np.int32)
    m = _mesh(v, t)
    # make the normals point outwards (away from the axis) whatever the winding came out as
    out = np.concatenate([ring[:, :2], np.zeros((len(ring), 1))], 1)
    if np.sum(m.normals[:len(ring)] * out) < 0:
        t = t[:, ::-1].copy()
        m = _mesh(v, t)
    return m


def calipers(vertices: np.ndarray, n_directions: int = 360) -> tuple[float, float]:
    """(mean, max) caliper width of a mesh across its local z axis: the width of the vertices' projection
    onto each of `n_directions` directions in the local xy plane (their Feret diameters). The mean is what a
    caliper reads on average when held across the fruit's axis at a random angle, the max the widest reading.
    For a lobed pepper both differ from the shape's nominal `diameter_m` (mean about 0.95 x, max 0.96-1.0 x)."""
    xy = np.asarray(vertices, np.float64)[:, :2]
    ang = np.linspace(0.0, np.pi, n_directions, endpoint=False)
    proj = xy @ np.stack([np.cos(ang), np.sin(ang)])
    width = proj.max(0) - proj.min(0)
    return float(width.mean()), float(width.max())
