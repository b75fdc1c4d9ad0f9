"""Triangle-mesh glasshouse row (floor, back wall, pipes, near and far plant rows with pepper fruits)
ray-cast with Open3D's RaycastingScene for exact depth, ids and view-independent shading.

World frame: x along the row (the driving direction), y towards the plants (left of the robot),
z up; the floor is z = 0. Units are metres.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import open3d as o3d

from synthetic.textures import fbm, value_noise

# Materials: each geometry gets one; shading and semantic class follow from it.
FLOOR, WALL, PIPE, STEM, LEAF, FRUIT = range(6)
STUFF_CLASS = {FLOOR: 0, WALL: 0, PIPE: 0, STEM: 1, LEAF: 1}
FRUIT_RGB = {2: (0.16, 0.42, 0.10), 3: (0.90, 0.55, 0.08), 4: (0.62, 0.05, 0.04)}


@dataclass(frozen=True)
class RowLayout:
    x_min_m: float
    x_max_m: float
    near_row_y_m: float
    far_row_y_m: float
    wall_y_m: float
    fruit_z_range_m: tuple[float, float]
    plant_spacing_m: float
    fruits_per_m: float


@dataclass
class Fruit:
    fruit_id: int
    class_id: int
    centre: np.ndarray
    diameter_m: float
    length_m: float
    near_row: bool


@dataclass
class Scene:
    raycaster: o3d.t.geometry.RaycastingScene
    material: np.ndarray
    """[n_geometries] material per geometry id."""
    instance: np.ndarray
    """[n_geometries] fruit id per geometry id (0 = stuff)."""
    klass: np.ndarray
    """[n_geometries] semantic class per geometry id."""
    fruits: list[Fruit] = field(default_factory=list)
    seed: int = 0


def _rot(axis: np.ndarray, angle: float) -> np.ndarray:
    axis = axis / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def box(lo, hi) -> tuple[np.ndarray, np.ndarray]:
    m = o3d.geometry.TriangleMesh.create_box(*(np.asarray(hi) - np.asarray(lo)))
    return np.asarray(m.vertices) + lo, np.asarray(m.triangles)


def cylinder(p0: np.ndarray, p1: np.ndarray, radius: float, res: int = 8) -> tuple[np.ndarray, np.ndarray]:
    d = p1 - p0
    m = o3d.geometry.TriangleMesh.create_cylinder(radius=radius, height=float(np.linalg.norm(d)),
                                                  resolution=res, split=1)
    v = np.asarray(m.vertices).copy()
    z = np.array([0.0, 0.0, 1.0])
    u = d / np.linalg.norm(d)
    axis = np.cross(z, u)
    r = np.eye(3) if np.linalg.norm(axis) < 1e-9 else _rot(axis, float(np.arccos(np.clip(z @ u, -1, 1))))
    return v @ r.T + (p0 + p1) / 2, np.asarray(m.triangles)


def leaf(centre: np.ndarray, length: float, width: float, yaw: float, pitch: float, curl: float,
         res: int = 6) -> tuple[np.ndarray, np.ndarray]:
    """A curved elliptic leaf blade as a small grid of triangles."""
    s = np.linspace(-1, 1, res + 1)
    uu, vv = np.meshgrid(s, s, indexing="ij")
    half_w = width / 2 * np.sqrt(np.clip(1 - uu ** 2, 0.02, 1))
    x = uu * length / 2
    y = vv * half_w
    z = curl * (uu ** 2 + 0.5 * vv ** 2) * length
    v = np.stack([x.ravel(), y.ravel(), z.ravel()], 1)
    r = _rot(np.array([0.0, 0.0, 1.0]), yaw) @ _rot(np.array([0.0, 1.0, 0.0]), pitch)
    idx = np.arange((res + 1) ** 2).reshape(res + 1, res + 1)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    tris = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return v @ r.T + centre, tris


def pepper(centre: np.ndarray, diameter: float, length: float, tilt: np.ndarray, phase: float,
           res: int = 18) -> tuple[np.ndarray, np.ndarray]:
    """A blocky, three/four-lobed sweet pepper, tapered at the bottom, axis roughly vertical."""
    m = o3d.geometry.TriangleMesh.create_sphere(radius=1.0, resolution=res)
    v = np.asarray(m.vertices).copy()
    theta = np.arctan2(v[:, 1], v[:, 0])
    zn = v[:, 2]
    lobes = 1 + 0.09 * np.cos(4 * theta + phase) * (1 - zn ** 2) ** 0.5
    blocky = 1 + 0.12 * (1 - np.abs(zn)) ** 2
    taper = 1 - 0.25 * np.clip(-zn, 0, 1) ** 1.5
    rxy = diameter / 2 * lobes * blocky * taper / 1.12
    v = np.stack([v[:, 0] * rxy, v[:, 1] * rxy, zn * length / 2], 1)
    r = _rot(np.array([1.0, 0.0, 0.0]), tilt[0]) @ _rot(np.array([0.0, 1.0, 0.0]), tilt[1])
    return v @ r.T + centre, np.asarray(m.triangles)


class SceneBuilder:
    def __init__(self) -> None:
        self.parts: list[tuple[np.ndarray, np.ndarray, int, int, int]] = []

    def add(self, mesh: tuple[np.ndarray, np.ndarray], material: int, instance: int = 0, klass: int = -1) -> None:
        self.parts.append((mesh[0], mesh[1], material, instance, STUFF_CLASS.get(material, klass)))

    def build(self, fruits: list[Fruit], seed: int) -> Scene:
        rc = o3d.t.geometry.RaycastingScene()
        mats, insts, klasses = [], [], []
        for v, t, mat, inst, k in self.parts:
            gid = rc.add_triangles(o3d.core.Tensor(v.astype(np.float32)), o3d.core.Tensor(t.astype(np.uint32)))
            if gid != len(mats):
                raise RuntimeError("Open3D geometry ids are not sequential")
            mats.append(mat)
            insts.append(inst)
            klasses.append(k)
        return Scene(rc, np.array(mats), np.array(insts), np.array(klasses), fruits, seed)


def plant_row(b: SceneBuilder, rng: np.random.Generator, layout: RowLayout, row_y: float, near: bool,
              fruits: list[Fruit], class_probs: tuple[float, float, float]) -> None:
    """Stems on a line y = row_y with leaves and fruits hanging around camera height."""
    xs = np.arange(layout.x_min_m, layout.x_max_m, layout.plant_spacing_m)
    xs = xs + rng.uniform(-0.05, 0.05, len(xs))
    top = layout.fruit_z_range_m[1] + 0.6
    for x in xs:
        base = np.array([x, row_y + rng.uniform(-0.03, 0.03), 0.0])
        tip = np.array([x + rng.uniform(-0.05, 0.05), base[1] + rng.uniform(-0.04, 0.04), top])
        b.add(cylinder(base, tip, 0.008), STEM)
        for _ in range(rng.poisson(16)):
            z = rng.uniform(0.15, top)
            stem_pt = base + (tip - base) * z / top
            yaw = rng.uniform(0, 2 * np.pi)
            length = rng.uniform(0.08, 0.16)
            offset = np.array([np.cos(yaw), np.sin(yaw), 0.0]) * length * 0.55
            # keep leaves mostly out of the space between the camera and the fruits
            if near and offset[1] < -0.02 and layout.fruit_z_range_m[0] - 0.05 < z < layout.fruit_z_range_m[1] + 0.05 \
                    and rng.random() < 0.6:
                offset[1] = abs(offset[1])
                yaw = np.arctan2(offset[1], offset[0])
            b.add(leaf(stem_pt + offset, length, length * rng.uniform(0.45, 0.6), yaw,
                       rng.uniform(-0.5, 0.3), rng.uniform(0.05, 0.2)), LEAF)
    n_fruits = rng.poisson(layout.fruits_per_m * (layout.x_max_m - layout.x_min_m))
    placed: list[np.ndarray] = [f.centre for f in fruits if f.near_row == near]
    for _ in range(n_fruits):
        for _try in range(20):
            d = rng.uniform(0.06, 0.09)
            length = d * rng.uniform(1.0, 1.3)
            c = np.array([rng.uniform(layout.x_min_m, layout.x_max_m),
                          row_y - rng.uniform(0.0, 0.06),
                          rng.uniform(*layout.fruit_z_range_m)])
            if all(np.linalg.norm(c - p) > 0.105 for p in placed):
                break
        else:
            continue
        placed.append(c)
        klass = int(rng.choice([2, 3, 4], p=class_probs))
        fid = len(fruits) + 1
        fruits.append(Fruit(fid, klass, c, d, length, near))
        b.add(pepper(c, d, length, rng.uniform(-0.25, 0.25, 2), rng.uniform(0, 2 * np.pi)), FRUIT, fid, klass)
        b.add(cylinder(c + [0, 0, length * 0.45], c + [rng.uniform(-0.02, 0.02), 0.0, length * 0.5 + 0.05], 0.005,
                       res=6), STEM)


def build_scene(layout: RowLayout, seed: int, class_probs: tuple[float, float, float] = (0.4, 0.25, 0.35)) -> Scene:
    rng = np.random.default_rng(seed)
    b = SceneBuilder()
    pad = 1.5
    b.add(box([layout.x_min_m - pad, -2.0, -0.02], [layout.x_max_m + pad, layout.wall_y_m + 0.1, 0.0]), FLOOR)
    b.add(box([layout.x_min_m - pad, layout.wall_y_m, 0.0], [layout.x_max_m + pad, layout.wall_y_m + 0.1, 3.0]), WALL)
    for z in (0.12, 0.22):  # heating pipes along the near row, as in a glasshouse
        b.add(cylinder(np.array([layout.x_min_m - pad, layout.near_row_y_m - 0.25, z]),
                       np.array([layout.x_max_m + pad, layout.near_row_y_m - 0.25, z]), 0.025, res=12), PIPE)
    fruits: list[Fruit] = []
    plant_row(b, rng, layout, layout.near_row_y_m, True, fruits, class_probs)
    plant_row(b, rng, layout, layout.far_row_y_m, False, fruits, class_probs)
    return b.build(fruits, seed)


def shade(scene: Scene, points: np.ndarray, normals: np.ndarray, gids: np.ndarray) -> np.ndarray:
    """View-independent colour [N, 3] in [0, 1]: albedo from 3D textures times Lambert (two-sided)."""
    mat = scene.material[gids]
    s = scene.seed
    albedo = np.zeros((len(points), 3))
    for m in np.unique(mat):
        sel = mat == m
        p = points[sel]
        if m == FLOOR:
            n = fbm(p, 0.15, 3, s + 1)
            speck = value_noise(p, 0.01, s + 2) > 0.8
            a = np.array([0.42, 0.38, 0.33]) * (0.6 + 0.7 * n)[:, None]
            a[speck] *= 0.55
        elif m == WALL:
            n = fbm(p, 0.3, 3, s + 3)
            panel = ((np.floor(p[:, 0] / 0.6) + np.floor(p[:, 2] / 0.6)) % 2)
            a = np.array([0.72, 0.74, 0.70]) * (0.75 + 0.25 * n + 0.08 * panel)[:, None]
        elif m == PIPE:
            a = np.array([0.78, 0.78, 0.80]) * (0.8 + 0.2 * value_noise(p, 0.05, s + 4))[:, None]
        elif m == STEM:
            n = value_noise(p, 0.02, s + 5)
            a = np.array([0.30, 0.45, 0.16]) * (0.7 + 0.5 * n)[:, None]
        elif m == LEAF:
            n = fbm(p, 0.04, 3, s + 6)
            vein = value_noise(p, 0.006, s + 7)
            a = np.stack([0.10 + 0.12 * n, 0.33 + 0.25 * n, 0.07 + 0.06 * n], 1) * (0.85 + 0.3 * vein)[:, None]
        else:  # FRUIT
            klass = scene.klass[gids[sel]]
            base = np.array([FRUIT_RGB[int(k)] for k in klass])
            n = fbm(p, 0.03, 2, s + 8)
            blotch = value_noise(p, 0.025, s + 9)
            mixed = klass == 3
            base[mixed] = np.where((blotch[mixed] > 0.55)[:, None], [0.35, 0.42, 0.06], base[mixed])
            a = base * (0.75 + 0.45 * n)[:, None] * (0.92 + 0.16 * value_noise(p, 0.004, s + 10))[:, None]
        albedo[sel] = a
    light = np.array([0.3, -0.5, 0.8])
    light /= np.linalg.norm(light)
    lambert = np.abs(normals @ light)
    return np.clip(albedo * (0.45 + 0.75 * lambert)[:, None], 0, 1)


def render(scene: Scene, c2w: np.ndarray, fx: float, fy: float, cx: float, cy: float, width: int, height: int,
           supersample: int = 2) -> dict[str, np.ndarray]:
    """Ray-cast one OpenCV camera. Returns rgb [H, W, 3] uint8, depth [H, W] float32 metres along the
    optical axis (0 = no hit), semantic [H, W] uint8 and instance [H, W] uint16 (fruit ids)."""
    def cast(ss: int):
        u = (np.arange(width * ss) + 0.5) / ss
        v = (np.arange(height * ss) + 0.5) / ss
        uu, vv = np.meshgrid(u, v)
        d_cam = np.stack([(uu - cx) / fx, (vv - cy) / fy, np.ones_like(uu)], -1).reshape(-1, 3)
        d_world = d_cam @ c2w[:3, :3].T
        origin = np.broadcast_to(c2w[:3, 3], d_world.shape)
        rays = o3d.core.Tensor(np.concatenate([origin, d_world], 1).astype(np.float32))
        hit = scene.raycaster.cast_rays(rays)
        t = hit["t_hit"].numpy().astype(np.float64)
        gid = hit["geometry_ids"].numpy().astype(np.int64)
        normals = hit["primitive_normals"].numpy().astype(np.float64)
        return t, gid, normals, origin, d_world

    t, gid, normals, origin, d_world = cast(supersample)
    ok = np.isfinite(t) & (gid != o3d.t.geometry.RaycastingScene.INVALID_ID)
    rgb = np.zeros((len(t), 3))
    pts = origin[ok] + d_world[ok] * t[ok, None]
    rgb[ok] = shade(scene, pts, normals[ok], gid[ok])
    ss = supersample
    rgb = rgb.reshape(height, ss, width, ss, 3).mean((1, 3)) if ss > 1 else rgb.reshape(height, width, 3)
    # depth and labels from the pixel-centre ray
    t1, gid1, _, _, _ = cast(1) if ss > 1 else (t, gid, None, None, None)
    ok1 = np.isfinite(t1) & (gid1 != o3d.t.geometry.RaycastingScene.INVALID_ID)
    depth = np.where(ok1, t1, 0.0).reshape(height, width)  # t is along d_cam with z = 1: z-depth
    safe = np.where(ok1, gid1, 0)
    sem = np.where(ok1, scene.klass[safe], 0).reshape(height, width)
    inst = np.where(ok1, scene.instance[safe], 0).reshape(height, width)
    return {"rgb": np.round(rgb * 255).astype(np.uint8), "depth": depth.astype(np.float32),
            "semantic": sem.astype(np.uint8), "instance": inst.astype(np.uint16)}
