"""The glasshouse row as triangle meshes: floor, back wall, heating pipes, posts, a near row and a far row
of sweet-pepper plants (stems, leaves, fruits), merged into one Open3D RaycastingScene.

World frame (ROS REP-103): x along the row (the driving direction), y left (towards the plants), z up;
the floor is z = 0; metres. Every triangle belongs to a part (one stem, leaf, fruit, ...) that carries
its material, semantic class, instance id (fruit id, 0 for stuff) and local frame (for textures).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from synthetic import meshes, season
from synthetic.meshes import Mesh

if TYPE_CHECKING:  # Open3D is imported where the scene is built, so the model stages run without it (a GPU machine)
    import open3d as o3d

FLOOR, WALL, PIPE, POST, STEM, LEAF, FRUIT = range(7)
MATERIALS = ("floor", "wall", "pipe", "post", "stem", "leaf", "fruit")
BACKGROUND, PLANT = 0, 1
GREEN, MIXED, RED = 2, 3, 4


@dataclass(frozen=True)
class RowLayout:
    """Where things are, in world metres (the stage derives it from the camera path)."""

    near_row_y_m: float
    far_row_y_m: float
    wall_y_m: float
    x_range_m: tuple[float, float]
    """Stretch of floor and wall (each gets a further 4 m margin)."""
    near_plant_x_m: tuple[float, float]
    """Stretch of the near row that gets plants (the rest is never in view)."""
    near_leaf_z_m: tuple[float, float]
    """Height band of the near row that gets leaves (stems run the full height)."""
    far_plant_x_m: tuple[float, float]
    far_leaf_z_m: tuple[float, float]
    near_fruit_x_m: tuple[float, float]
    near_fruit_z_m: tuple[float, float]
    far_fruit_x_m: tuple[float, float]
    far_fruit_z_m: tuple[float, float]
    fruits_per_m: float
    ripeness_mix: tuple[float, float, float]
    """Relative shares of green, mixed and red fruits."""
    plant_spacing_m: float = 0.25
    node_spacing_m: float = 0.06
    leaf_size: float = 1.0
    plant_height_m: float = 2.4


@dataclass(frozen=True)
class Fruit:
    fruit_id: int
    class_id: int
    centre: tuple[float, float, float]
    diameter_m: float
    """mean caliper width across the fruit's axis, measured on its mesh (meshes.calipers)."""
    length_m: float
    near_row: bool
    diameter_max_m: float = float("nan")
    """widest caliper reading across the axis (meshes.calipers)."""
    diameter_nominal_m: float = float("nan")
    """the shape parameter the mesh was built from (meshes.pepper's diameter_m)."""


@dataclass
class Scene:
    raycaster: o3d.t.geometry.RaycastingScene
    part_of_triangle: np.ndarray
    """[T] part index of every triangle."""
    corner_normals: np.ndarray
    """[T, 3, 3] float32 vertex normals at the triangle corners (smooth shading)."""
    material: np.ndarray
    """[P] material of every part."""
    klass: np.ndarray
    """[P] semantic class id."""
    instance: np.ndarray
    """[P] fruit id (0 = stuff)."""
    rot: np.ndarray
    """[P, 3, 3] local-to-world rotation of the part's own frame."""
    origin: np.ndarray
    """[P, 3] the part's local origin in the world."""
    param: np.ndarray
    """[P, 4] per-part texture parameters (meaning depends on the material)."""
    fruits: list[Fruit]
    seed: int
    lives: dict[int, season.FruitLife] | None = None
    """fruit id -> its course over the season (every fruit planned up to the scene's day, present or not)."""
    near_by_id: dict[int, bool] | None = None
    """fruit id -> in the near row (every fruit of `lives`)."""


class SceneBuilder:
    """Collects placed meshes with their attributes, then merges them into one raycasting scene."""

    def __init__(self) -> None:
        self.meshes: list[Mesh] = []
        self.attrs: list[tuple[int, int, int]] = []
        self.frames: list[tuple[np.ndarray, np.ndarray]] = []
        self.params: list[np.ndarray] = []
        self.n_leaves = 0

    def add(self, local: Mesh, rot: np.ndarray, origin: np.ndarray, material: int, klass: int,
            instance: int = 0, param: tuple[float, ...] = ()) -> None:
        self.meshes.append(local.transformed(rot, origin))
        self.attrs.append((material, klass, instance))
        self.frames.append((np.asarray(rot, np.float32), np.asarray(origin, np.float32)))
        p = np.full(4, np.nan, np.float32)
        p[:len(param)] = param
        self.params.append(p)

    def build(self, fruits: list[Fruit], seed: int) -> Scene:
        offsets = np.cumsum([0] + [len(m.vertices) for m in self.meshes])
        verts = np.concatenate([m.vertices for m in self.meshes]).astype(np.float32)
        tris = np.concatenate([m.triangles + o for m, o in zip(self.meshes, offsets)]).astype(np.uint32)
        part = np.concatenate([np.full(len(m.triangles), i, np.int32) for i, m in enumerate(self.meshes)])
        normals = np.concatenate([m.corner_normals() for m in self.meshes]).astype(np.float32)
        import open3d as o3d

        rc = o3d.t.geometry.RaycastingScene()
        rc.add_triangles(o3d.core.Tensor(verts), o3d.core.Tensor(tris))
        a = np.array(self.attrs)
        return Scene(rc, part, normals, a[:, 0].astype(np.int8), a[:, 1].astype(np.uint8),
                     a[:, 2].astype(np.uint16), np.stack([f[0] for f in self.frames]),
                     np.stack([f[1] for f in self.frames]), np.stack(self.params), fruits, seed)


@dataclass(frozen=True)
class _FruitPlan:
    near: bool
    class_id: int
    centre: np.ndarray
    rot: np.ndarray
    diameter_m: float
    length_m: float
    n_lobes: int
    phase: float
    hue: float
    stalk_to: np.ndarray
    anchor: np.ndarray | None = None
    """point on the stem the fruit hangs from; centre = anchor + (diameter / 2 + gap_m) * direction."""
    direction: np.ndarray | None = None
    gap_m: float = 0.0


@dataclass(frozen=True)
class Season:
    """Which date of the season the scene shows (synthetic/season.py)."""

    day: float = 0.0
    """days since the first recording (0 = the row as planned)."""
    growth_rate_scale: float = 1.0
    """multiplies every fruit's growth speed."""
    fruit_set_per_m_per_week: float = 1.5
    """new fruits setting per metre of row and week."""


def _stem_polyline(rng: np.random.Generator, x: float, y: float, height_m: float, n: int = 14) -> np.ndarray:
    z = np.linspace(0.0, height_m, n)
    wander = np.cumsum(rng.normal(0.0, 0.012, (n, 2)), 0)
    wander -= wander[0]
    return np.stack([x + wander[:, 0], y + wander[:, 1], z], 1)


def _point_on_stem(stem: np.ndarray, z: float) -> np.ndarray:
    return np.array([np.interp(z, stem[:, 2], stem[:, 0]), np.interp(z, stem[:, 2], stem[:, 1]), z])


def _plan_fruits(rng: np.random.Generator, layout: RowLayout, stems: list[np.ndarray], near: bool,
                 x_range: tuple[float, float], z_range: tuple[float, float]) -> list[_FruitPlan]:
    """Fruits hang from the stems on the aisle side (towards -y, the camera), without touching each other."""
    n = rng.poisson(layout.fruits_per_m * max(0.0, x_range[1] - x_range[0]))
    mix = np.asarray(layout.ripeness_mix, np.float64)
    mix = mix / mix.sum()
    stem_x = np.array([s[0, 0] for s in stems])
    plans: list[_FruitPlan] = []
    for _ in range(n):
        for _attempt in range(40):
            d = rng.uniform(0.06, 0.09)
            length = rng.uniform(max(0.07, 0.95 * d), min(0.11, 1.45 * d))
            x_t = rng.uniform(*x_range)
            stem = stems[int(np.argmin(np.abs(stem_x - x_t)))]
            z = rng.uniform(*z_range)
            az = -np.pi / 2 + rng.normal(0.0, 0.8)
            reach = 0.5 * d + rng.uniform(0.008, 0.03)
            anchor, direction = _point_on_stem(stem, z), np.array([np.cos(az), np.sin(az), 0.0])
            c = anchor + reach * direction
            radius = 0.5 * max(d, length)
            if any(np.linalg.norm(c - p.centre) < 0.9 * (radius + 0.5 * max(p.diameter_m, p.length_m)) + 0.004
                   for p in plans):
                continue
            if any(np.linalg.norm((c - _point_on_stem(s, z))[:2]) < 0.5 * d + 0.01 for s in stems
                   if abs(s[0, 0] - c[0]) < 0.3):
                continue
            break
        else:
            continue
        tilt_dir, tilt, spin = rng.uniform(0, 2 * np.pi), np.radians(rng.uniform(0, 18)), rng.uniform(0, 2 * np.pi)
        rot = meshes.rotation([np.cos(tilt_dir), np.sin(tilt_dir), 0.0], tilt) @ meshes.rotation([0, 0, 1], spin)
        stalk_to = _point_on_stem(stem, min(z + 0.5 * length + rng.uniform(0.02, 0.05), layout.plant_height_m))
        plans.append(_FruitPlan(near, int(rng.choice([GREEN, MIXED, RED], p=mix)), c, rot, d, length,
                                int(rng.choice([3, 4], p=[0.35, 0.65])), rng.uniform(0, 2 * np.pi),
                                rng.uniform(0, 1), stalk_to, anchor, direction, reach - 0.5 * d))
    return plans


def _new_fruits(seed: int, layout: RowLayout, rows: list[tuple[bool, list[np.ndarray]]], taken: list[_FruitPlan],
                season_: Season) -> list[tuple[_FruitPlan, season.FruitLife]]:
    """Fruits that set after the first recording, up to season_.day: planned week by week from their own
    streams ([seed, 14, week]), so a later date extends an earlier one's list. They keep clear of every other
    fruit at its final size (`taken`, which this extends) and of the stems."""
    out: list[tuple[_FruitPlan, season.FruitLife]] = []
    for week in range(int(np.ceil(season_.day / season.WEEK_DAYS))):
        rng = np.random.default_rng([seed, 14, week])
        for near, stems in rows:
            x_range, z_range = ((layout.near_fruit_x_m, layout.near_fruit_z_m) if near
                                else (layout.far_fruit_x_m, layout.far_fruit_z_m))
            stem_x = np.array([st[0, 0] for st in stems])
            n = rng.poisson(season_.fruit_set_per_m_per_week * max(0.0, x_range[1] - x_range[0]))
            for _ in range(n):
                life = season.life_of_new_fruit(week * season.WEEK_DAYS + rng.uniform(0.0, season.WEEK_DAYS), rng,
                                                season_.growth_rate_scale)
                d_end = life.d_max_m
                for _attempt in range(40):
                    x_t, z = rng.uniform(*x_range), rng.uniform(*z_range)
                    stem = stems[int(np.argmin(np.abs(stem_x - x_t)))]
                    az = -np.pi / 2 + rng.normal(0.0, 0.8)
                    gap = rng.uniform(0.008, 0.03)
                    anchor, direction = _point_on_stem(stem, z), np.array([np.cos(az), np.sin(az), 0.0])
                    c = anchor + (0.5 * d_end + gap) * direction
                    if any(np.linalg.norm(c - p.centre) < 0.9 * (0.6 * d_end + 0.5 * max(p.diameter_m, p.length_m))
                           + 0.004 for p in taken):
                        continue
                    if any(np.linalg.norm((c - _point_on_stem(s, z))[:2]) < 0.5 * d_end + 0.01 for s in stems
                           if abs(s[0, 0] - c[0]) < 0.3):
                        continue
                    break
                else:
                    continue
                tilt_dir, tilt, spin = rng.uniform(0, 2 * np.pi), np.radians(rng.uniform(0, 18)), rng.uniform(0, 2 * np.pi)
                rot = meshes.rotation([np.cos(tilt_dir), np.sin(tilt_dir), 0.0], tilt) @ meshes.rotation([0, 0, 1], spin)
                d0 = life.d0_m
                length = d0 * rng.uniform(1.0, 1.3)
                stalk_to = _point_on_stem(stem, min(z + 0.6 * d_end + rng.uniform(0.02, 0.05), layout.plant_height_m))
                plan = _FruitPlan(near, season.GREEN, anchor + (0.5 * d0 + gap) * direction, rot, d0, length,
                                  int(rng.choice([3, 4], p=[0.35, 0.65])), rng.uniform(0, 2 * np.pi), rng.uniform(0, 1),
                                  stalk_to, anchor, direction, gap)
                # reserve the room it grows into
                taken.append(_FruitPlan(near, season.GREEN, c, rot, d_end, length * d_end / d0, 3, 0.0, 0.0, stalk_to))
                out.append((plan, life))
    return out


def _on_day(p: _FruitPlan, life: season.FruitLife, day: float) -> _FruitPlan:
    """The plan as the fruit is on `day`: its size, class and (pushed off the stem as it grows) centre."""
    d = life.diameter_m(day)
    if d == p.diameter_m and life.class_id(day) == p.class_id:
        return p
    centre = p.anchor + (0.5 * d + p.gap_m) * p.direction if d != p.diameter_m else p.centre
    return _FruitPlan(p.near, life.class_id(day), centre, p.rot, d, p.length_m * d / p.diameter_m, p.n_lobes, p.phase,
                      p.hue, p.stalk_to, p.anchor, p.direction, p.gap_m)


def _add_leaves(b: SceneBuilder, rng: np.random.Generator, layout: RowLayout, stem: np.ndarray, klass: int,
                row_y: float, z_band: tuple[float, float], avoid: list[_FruitPlan], season_: Season,
                seed: int) -> None:
    """Leaves at nodes up the stem (within z_band), spiralling by the golden angle, kept out of the fruits;
    after the first recording each leaf has turned and grown a little (season.leaf_motion, from the leaf's
    own stream [seed, 13, leaf number], so the row's layout stays the first date's)."""
    z = max(0.12, z_band[0]) + rng.uniform(0.0, layout.node_spacing_m)
    az = rng.uniform(0, 2 * np.pi)
    centres = np.array([p.centre for p in avoid]) if avoid else np.zeros((0, 3))
    radii = np.array([0.5 * max(p.diameter_m, p.length_m) for p in avoid])
    while z < min(layout.plant_height_m - 0.1, z_band[1]):
        node = _point_on_stem(stem, z)
        for _ in range(1 + rng.binomial(2, 0.35)):
            az += np.radians(137.5) + rng.normal(0.0, 0.35)
            length = rng.uniform(0.10, 0.19) * layout.leaf_size
            width = length * rng.uniform(0.45, 0.6)
            for _try in range(4):
                elev = rng.uniform(np.radians(-10), np.radians(40))
                rot = meshes.rotation([0, 0, 1], az) @ meshes.rotation([0, 1, 0], -elev) @ \
                    meshes.rotation([1, 0, 0], rng.normal(0.0, 0.7))
                base = node + rot[:, 0] * 0.012
                samples = base + np.outer([0.25, 0.5, 0.8], rot[:, 0]) * length
                if not len(centres) or np.all(np.linalg.norm(samples[:, None] - centres[None], axis=2)
                                              > radii[None] + 0.25 * width + 0.01):
                    curl, twist = rng.uniform(0.1, 0.5), rng.uniform(0.05, 0.3)
                    tex = rng.random()
                    b.n_leaves += 1
                    grow = 1.0
                    if season_.day > 0:
                        axis, angle, grow = season.leaf_motion(np.random.default_rng([seed, 13, b.n_leaves]),
                                                               season_.day)
                        rot = meshes.rotation(axis, angle) @ rot
                    b.add(meshes.leaf_blade(length * grow, width * grow, curl, twist, res=6),
                          rot, base, LEAF, klass, param=(tex, length * grow, width * grow, row_y))
                    break
                az += rng.uniform(1.0, 2.0)
        z += layout.node_spacing_m * rng.uniform(0.7, 1.3)


def _plant_row(b: SceneBuilder, rng: np.random.Generator, layout: RowLayout, row_y: float, near: bool,
               season_: Season, seed: int) -> tuple[list[np.ndarray], list[_FruitPlan]]:
    px, lz = (layout.near_plant_x_m, layout.near_leaf_z_m) if near else (layout.far_plant_x_m, layout.far_leaf_z_m)
    xs = np.arange(px[0], px[1], layout.plant_spacing_m)
    xs = xs + rng.uniform(-0.3, 0.3, len(xs)) * layout.plant_spacing_m
    stems = [_stem_polyline(rng, x, row_y + rng.uniform(-0.04, 0.04), layout.plant_height_m) for x in xs]
    fx, fz = (layout.near_fruit_x_m, layout.near_fruit_z_m) if near else (layout.far_fruit_x_m, layout.far_fruit_z_m)
    plans = _plan_fruits(rng, layout, stems, near, fx, fz)
    klass = PLANT if near else BACKGROUND  # far-row foliage is background (data/README.md)
    for stem in stems:
        radii = np.linspace(0.010, 0.005, len(stem))
        b.add(meshes.tube(stem, radii, res=7), np.eye(3), np.zeros(3), STEM, klass, param=(rng.random(), 0, 0, row_y))
        _add_leaves(b, rng, layout, stem, klass, row_y, lz, [p for p in plans if abs(p.centre[0] - stem[0, 0]) < 0.4],
                    season_, seed)
    return stems, plans


def build_scene(layout: RowLayout, seed: int, season_: Season = Season()) -> Scene:
    """The whole row on day season_.day; fruit ids are 1.. with the near row first, each row ordered along x
    (as planned for the first recording), then the fruits that set later in the order they set. A fruit keeps
    its id over the season; harvested and not yet set fruits are left out (ids then have gaps)."""
    rng = np.random.default_rng([seed, 11])
    b = SceneBuilder()
    x0, x1 = layout.x_range_m
    far_y = layout.far_row_y_m
    b.add(meshes.box([x0 - 4, -2.0, -0.05], [x1 + 4, layout.wall_y_m + 0.1, 0.0]), np.eye(3), np.zeros(3),
          FLOOR, BACKGROUND)
    b.add(meshes.box([x0 - 4, layout.wall_y_m, 0.0], [x1 + 4, layout.wall_y_m + 0.1, 4.0]), np.eye(3),
          np.zeros(3), WALL, BACKGROUND)
    for aisle_y in ((layout.near_row_y_m + far_y) / 2, far_y + 0.5):  # heating pipe rails in the aisles
        for dy in (-0.28, 0.28):
            pts = np.array([[x0 - 4, aisle_y + dy, 0.11], [x1 + 4, aisle_y + dy, 0.11]])
            b.add(meshes.tube(pts, 0.026, res=12), np.eye(3), np.zeros(3), PIPE, BACKGROUND)
    for x in np.arange(np.floor((x0 - 4) / 3.2) * 3.2, x1 + 4, 3.2):  # glasshouse posts behind the far row
        pts = np.array([[x, far_y + 0.35, 0.0], [x, far_y + 0.35, 4.0]])
        b.add(meshes.tube(pts, 0.035, res=10), np.eye(3), np.zeros(3), POST, BACKGROUND)
    near_stems, near_plans = _plant_row(b, rng, layout, layout.near_row_y_m, True, season_, seed)
    far_stems, far_plans = _plant_row(b, rng, layout, far_y, False, season_, seed)
    plans = sorted(near_plans, key=lambda p: p.centre[0]) + sorted(far_plans, key=lambda p: p.centre[0])
    lives = [season.life_on_plant(p.class_id, p.diameter_m, np.random.default_rng([seed, 12, fid]),
                                  season_.growth_rate_scale) for fid, p in enumerate(plans, start=1)]
    if season_.day > 0:
        grown = [_on_day(p, life, 1e4) for p, life in zip(plans, lives)]
        new = _new_fruits(seed, layout, [(True, near_stems), (False, far_stems)], grown, season_)
        plans += [p for p, _ in new]
        lives += [life for _, life in new]
    fruits = []
    lives_by_id: dict[int, season.FruitLife] = {}
    near_by_id: dict[int, bool] = {}
    for fid, (p, life) in enumerate(zip(plans, lives), start=1):
        lives_by_id[fid] = life
        near_by_id[fid] = p.near
        if season_.day > 0:
            if not life.present(season_.day):
                continue
            p = _on_day(p, life, season_.day)
        stalk_klass = PLANT if p.near else BACKGROUND
        mesh = meshes.pepper(p.diameter_m, p.length_m, p.n_lobes, p.phase)
        width_mean, width_max = meshes.calipers(mesh.vertices)
        b.add(mesh, p.rot, p.centre, FRUIT, p.class_id, fid,
              param=(p.hue, p.length_m, p.diameter_m, p.n_lobes + p.phase / (2 * np.pi)))
        top = p.centre + p.rot[:, 2] * 0.4 * p.length_m
        mid = (top + p.stalk_to) / 2 + np.array([0.0, 0.0, 0.01])
        b.add(meshes.tube(np.stack([top, mid, p.stalk_to]), 0.0045, res=6), np.eye(3), np.zeros(3), STEM,
              stalk_klass, param=(0.5, 0, 0, layout.near_row_y_m if p.near else far_y))
        fruits.append(Fruit(fid, p.class_id, tuple(float(v) for v in p.centre), width_mean, float(p.length_m),
                            p.near, width_max, float(p.diameter_m)))
    sc = b.build(fruits, seed)
    sc.lives, sc.near_by_id = lives_by_id, near_by_id
    return sc
