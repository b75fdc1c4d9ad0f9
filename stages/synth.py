"""Generate a synthetic glasshouse sweet-pepper row, with exact ground truth, in the formats a real recording has."""
from __future__ import annotations

import os
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import pandas as pd
import yaml

from pipeline import parallel
from pipeline.images import write_png
from pipeline.stage import StageContext
from sources.common import depth_to_mm
from synthetic import detector, render, scene, trajectory, writers

INPUTS: tuple[str, ...] = ()
OUTPUTS = ("raw",)

FIRST_STAMP_NS = 1_600_000_000_000_000_000
"""Stamp of the first camera frame of day 0; frame i is at FIRST_STAMP_NS + day * 86400 s + round(i * 1e9 / fps)."""
START_SHIFT_M = 0.25
"""On a later day (synth.day > 0) the robot starts up to this far (uniform, either way) from the first day's start
along the row; the planted stretch extends far enough beyond the first day's view to show plants there."""
ODOM_FRAME, BASE_FRAME, CAMERA_FRAME = "odom", "base_link", "camera_color_optical_frame"
TOPICS = {"color": "/camera/color/image_raw", "depth": "/camera/aligned_depth_to_color/image_raw",
          "info": "/camera/color/camera_info", "odom": "/odom", "tf_static": "/tf_static"}


PRESETS: dict[str, dict[str, int | float | bool]] = {
    "small": {"n_frames": 120, "width": 320, "height": 180, "fps": 15.0, "speed_m_per_s": 0.2, "n_labelled": 3,
              "write_bag": True, "supersample": 2},
    "bup20": {"n_frames": 450, "width": 1280, "height": 720, "fps": 15.0, "speed_m_per_s": 0.2, "n_labelled": 5,
              "write_bag": False, "supersample": 1},
}
"""Row sizes: `small` is the default row (1.6 m, 3 labelled frames); `bup20` has the size of a BUP20 /
RealSense recording: 1280x720 at 15 fps and 0.2 m/s, 450 frames = 6 m of row, a labelled frame every
metre (frames 75, 150, ..., 374: one metre from either end, so a window of +-40 frames fits around each).
The bup20 row writes no bag by default: its uncompressed images would be about 4.6 MB a frame (2 GB), and casts
one ray per pixel (supersample 1: a 1280x720 pixel is a quarter of a 640x360 one, so the camera's own blur
matters more than aliasing; it halves the ray casting)."""


@dataclass(frozen=True)
class Config:
    seed: int = 0
    """random seed: the same settings and seed give byte-identical files; every knob below is deterministic."""
    preset: Literal["small", "bup20"] = "small"
    """row size preset (PRESETS): fills n_frames, width, height, fps, speed_m_per_s, n_labelled and write_bag where
    they are not set; `bup20` is a real-size row (1280x720, 450 frames, 6 m)."""
    n_frames: int | None = None
    """camera frames in the row (None = the preset's; 120 at 15 fps and 0.2 m/s = 1.6 m of row)."""
    width: int | None = None
    """image width in pixels (None = the preset's)."""
    height: int | None = None
    """image height in pixels (None = the preset's)."""
    fov_x_deg: float = 69.0
    """horizontal field of view in degrees (RealSense D435 colour: 69); square pixels, centred principal point."""
    fps: float | None = None
    """camera frame rate in Hz (None = the preset's)."""
    speed_m_per_s: float | None = None
    """mean robot speed along the row in m/s (None = the preset's)."""
    base_height_m: float = 0.4
    """height of base_link above the floor (the odometry's z)."""
    camera_mast_m: float = 0.35
    """camera height above base_link (camera height above the floor = base_height_m + camera_mast_m)."""
    camera_lateral_m: float = 0.1
    """camera offset from base_link towards the row (+y)."""
    camera_distance_m: float = 0.6
    """distance from the camera to the near row's stem line."""
    far_row_distance_m: float = 2.0
    """distance from the camera to the far row's stem line (beyond the 1.5 m depth range); its fruits are
    in the ground truth with near_row = False, its foliage is background."""
    fruits_per_m: float = 12.0
    """fruits per metre of row, over the stretch of each row that the camera sees (near and far alike)."""
    ripeness_mix: tuple[float, ...] = (0.45, 0.2, 0.35)
    """relative shares of green (class 2), mixed (3) and red (4) fruits."""
    plant_spacing_m: float = 0.25
    """distance between stems along a row."""
    leaf_node_spacing_m: float = 0.06
    """mean vertical distance between leaf nodes on a stem (smaller = denser canopy)."""
    leaf_size: float = 1.0
    """scale of the leaves (1 = 10-19 cm long)."""
    texture_scale: float = 1.0
    """scale of every procedural texture's features (smaller = finer detail)."""
    odom_rate_hz: float = 50.0
    """odometry sample rate; odometry starts 0.2 s before the first frame and ends 0.2 s after the last."""
    odom_drift_m_per_m: float = 0.03
    """odometry translation drift (scale and sideways) accumulated per metre driven."""
    odom_yaw_drift_deg_per_m: float = 2.0
    """odometry heading drift accumulated per metre driven."""
    odom_noise_m: float = 0.002
    """white noise (standard deviation) on the odometry x and y."""
    det_miss_rate: float = 0.15
    """probability that the detector misses a visible fruit; fully visible fruits are missed less, occluded or
    cut-off ones more: 1 - (1 - rate)^(0.5 + 1.5 * hidden share)."""
    det_false_pos_rate: float = 0.3
    """expected false-positive fruit segments per frame (blobs on leaves, low score)."""
    det_boundary_px: int = 2
    """detected mask boundaries move in or out by a smooth offset of up to this many pixels."""
    det_merge_rate: float = 0.05
    """probability that a detected fruit is merged with a touching neighbour into one segment."""
    det_class_confusion_rate: float = 0.05
    """probability that a detected fruit gets a neighbouring ripeness class."""
    det_void_rate: float = 0.03
    """share of detector segment-border pixels left void (255) in the semantic PNG."""
    det_min_area_px: int = 12
    """detector segments smaller than this many pixels are dropped."""
    n_labelled: int | None = None
    """ground-truth labelled frames (annotations.json, seg/), evenly spread, never the first or last frame
    (None = the preset's)."""
    supersample: int | None = None
    """colour anti-aliasing: 1 = the pixel-centre ray only; 2 = centre plus the 4 pixel corners shared with the
    neighbours (quincunx, about 2 rays per pixel); s >= 3 = an s x s grid per pixel. Depth and labels always
    come from the pixel-centre ray (None = the preset's: 2 for small, 1 for bup20)."""
    detections_format: Literal["png_pair", "coco_panoptic", "coco_instances"] = "png_pair"
    """format of the detector output in pred_seg/: the project's PNG pair + scores.csv, COCO panoptic (JSON + PNG
    folder, as Detectron2 / Mask2Former write it) or COCO instance results (RLE masks + semantic PNGs for the
    stuff); all three hold the same segments (docs/detector_formats.md)."""
    write_bag: bool | None = None
    """also write the recording as a ROS 1 bag <SEQ>.bag (pixel-identical to the PNGs; None = the preset's:
    yes for small, no for bup20)."""
    workers: int = 0
    """render threads (0 = one per CPU core, at most 4); the output does not depend on it."""
    day: float = 0.0
    """days since the season's first recording (>= 0; 0 = the row as planned). The same seed on another day
    shows the same plants and fruits, grown, ripened, harvested and with new fruits set (synthetic/season.py);
    leaves have moved a little, the recording is `day` days later and the robot starts up to START_SHIFT_M
    elsewhere along the row with new odometry drift, its odometry starting at its own origin."""
    growth_rate_scale: float = 1.0
    """multiplies every fruit's growth speed over the season (> 0; 1 = a green pepper grows about 0.5-1.5 mm a
    day); only matters with day > 0."""
    fruit_set_per_m_per_week: float = 1.5
    """new fruits that set per metre of row and week over the season (>= 0); only matters with day > 0."""

    def __post_init__(self) -> None:
        if self.preset not in PRESETS:
            raise ValueError(f"synth.preset must be one of {sorted(PRESETS)}, got {self.preset!r}")
        for name, value in PRESETS[self.preset].items():  # a field left at None takes the preset's value
            if getattr(self, name) is None:
                object.__setattr__(self, name, value)
        positive = ("n_frames", "width", "height", "fps", "speed_m_per_s", "camera_distance_m", "odom_rate_hz",
                    "supersample", "plant_spacing_m", "leaf_node_spacing_m", "leaf_size", "texture_scale",
                    "growth_rate_scale")
        for name in positive:
            if not getattr(self, name) > 0:
                raise ValueError(f"synth.{name} must be > 0, got {getattr(self, name)}")
        non_negative = ("fruits_per_m", "odom_drift_m_per_m", "odom_yaw_drift_deg_per_m", "odom_noise_m",
                        "det_false_pos_rate", "det_boundary_px", "det_min_area_px", "n_labelled", "workers",
                        "base_height_m", "camera_mast_m", "day", "fruit_set_per_m_per_week")
        for name in non_negative:
            if getattr(self, name) < 0:
                raise ValueError(f"synth.{name} must be >= 0, got {getattr(self, name)}")
        for name in ("det_miss_rate", "det_merge_rate", "det_class_confusion_rate", "det_void_rate"):
            if not 0 <= getattr(self, name) <= 1:
                raise ValueError(f"synth.{name} must be in [0, 1], got {getattr(self, name)}")
        if not 0 < self.fov_x_deg < 170:
            raise ValueError(f"synth.fov_x_deg must be in (0, 170), got {self.fov_x_deg}")
        if self.far_row_distance_m < self.camera_distance_m + 0.5:
            raise ValueError(f"synth.far_row_distance_m ({self.far_row_distance_m}) must be at least 0.5 m beyond "
                             f"synth.camera_distance_m ({self.camera_distance_m})")
        if len(self.ripeness_mix) != 3 or min(self.ripeness_mix) < 0 or sum(self.ripeness_mix) <= 0:
            raise ValueError(f"synth.ripeness_mix must be 3 non-negative shares (green, mixed, red) with a positive "
                             f"sum, got {self.ripeness_mix}")
        if self.n_labelled and self.n_labelled > self.n_frames - 2:
            raise ValueError(f"synth.n_labelled ({self.n_labelled}) must be at most n_frames - 2 "
                             f"({self.n_frames - 2}): labelled frames are never the first or last frame")


SEASON_SETTINGS = ("day", "growth_rate_scale", "fruit_set_per_m_per_week")
"""Settings that change nothing on day 0 (left out of gt/synth_config.yaml there, so day 0 is the row it always was)."""


def intrinsics(cfg: Config) -> np.ndarray:
    """3x3 K: square pixels, principal point at the image centre (pixel centres at half-integers)."""
    f = cfg.width / 2 / np.tan(np.radians(cfg.fov_x_deg) / 2)
    return np.array([[f, 0.0, cfg.width / 2], [0.0, f, cfg.height / 2], [0.0, 0.0, 1.0]])


def frame_stamps(cfg: Config) -> np.ndarray:
    return (FIRST_STAMP_NS + int(round(cfg.day * 86_400e9)) +
            np.round(np.arange(cfg.n_frames) * 1e9 / cfg.fps).astype(np.int64))


def stream(cfg: Config, key: int, *more: int) -> np.random.Generator:
    """The random stream `key` of the row: [seed, key, ...] on day 0 (the streams rows always had), and a day's
    own stream [seed, key, 1000, day in seconds, ...] on a later day."""
    day = [] if cfg.day == 0 else [1000, int(round(cfg.day * 86_400))]
    return np.random.default_rng([cfg.seed, key, *day, *more])


def odometry_stamps(cfg: Config, frame_stamps_ns: np.ndarray) -> np.ndarray:
    """odom_rate_hz samples from 0.2 s before the first frame to at least 0.2 s after the last."""
    period_ns = 1e9 / cfg.odom_rate_hz
    t0 = frame_stamps_ns[0] - 200_000_000
    n = int(np.ceil((frame_stamps_ns[-1] + 200_000_000 - t0) / period_ns)) + 1
    return t0 + np.round(np.arange(n) * period_ns).astype(np.int64)


def labelled_frames(cfg: Config) -> list[int]:
    if not cfg.n_labelled:
        return []
    return sorted({int(i) for i in np.round(np.linspace(0, cfg.n_frames - 1, cfg.n_labelled + 2)[1:-1])})


def row_layout(cfg: Config, cam_x: np.ndarray, cam_y: float, cam_z: float, k: np.ndarray) -> scene.RowLayout:
    """Rows, fruit bands and plant stretch sized from what the camera path sees."""
    tan_x, tan_y = cfg.width / 2 / k[0, 0], cfg.height / 2 / k[1, 1]
    near_y, far_y = cam_y + cfg.camera_distance_m, cam_y + cfg.far_row_distance_m
    wall_y = far_y + 1.0
    x_lo, x_hi = float(cam_x.min()), float(cam_x.max())
    near_half_h = max(0.02, (cfg.camera_distance_m - 0.06) * tan_y - 0.03)
    far_half_h = max(0.05, cfg.far_row_distance_m * tan_y - 0.05)
    reach_near, reach_far = cfg.camera_distance_m * tan_x, cfg.far_row_distance_m * tan_x
    reach_wall = (wall_y - cam_y) * tan_x
    leaf_margin_m = 0.25
    return scene.RowLayout(
        near_row_y_m=near_y, far_row_y_m=far_y, wall_y_m=wall_y,
        x_range_m=(x_lo - reach_wall - 0.5, x_hi + reach_wall + 0.5),
        near_plant_x_m=(x_lo - reach_near - 0.4, x_hi + reach_near + 0.4),
        near_leaf_z_m=(cam_z - (cfg.camera_distance_m + 0.2) * tan_y - leaf_margin_m,
                       cam_z + (cfg.camera_distance_m + 0.2) * tan_y + leaf_margin_m),
        far_plant_x_m=(x_lo - reach_far - 0.4, x_hi + reach_far + 0.4),
        far_leaf_z_m=(cam_z - (cfg.far_row_distance_m + 0.4) * tan_y - leaf_margin_m,
                      cam_z + (cfg.far_row_distance_m + 0.4) * tan_y + leaf_margin_m),
        near_fruit_x_m=(x_lo - reach_near, x_hi + reach_near),
        near_fruit_z_m=(max(0.2, cam_z - near_half_h), cam_z + near_half_h),
        far_fruit_x_m=(x_lo - reach_far, x_hi + reach_far),
        far_fruit_z_m=(max(0.3, cam_z - far_half_h), min(2.1, cam_z + far_half_h)),
        fruits_per_m=cfg.fruits_per_m, ripeness_mix=tuple(cfg.ripeness_mix), plant_spacing_m=cfg.plant_spacing_m,
        node_spacing_m=cfg.leaf_node_spacing_m, leaf_size=cfg.leaf_size,
        plant_height_m=max(2.4, cam_z + far_half_h + 0.3))


def odometry_twist(stamps_ns: np.ndarray, poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Body-frame linear [K, 3] and angular [K, 3] velocities of a pose sequence (finite differences)."""
    t = (stamps_ns - stamps_ns[0]) / 1e9
    if len(t) < 2:
        return np.zeros((len(t), 3)), np.zeros((len(t), 3))
    v_world = np.gradient(poses[:, :3, 3], t, axis=0)
    linear = np.einsum("kji,kj->ki", poses[:, :3, :3], v_world)
    yaw = np.unwrap(np.arctan2(poses[:, 1, 0], poses[:, 0, 0]))
    angular = np.zeros((len(t), 3))
    angular[:, 2] = np.gradient(yaw, t)
    return linear, angular


def season_table(sc: scene.Scene, day: float) -> pd.DataFrame:
    """gt/season.parquet: every fruit planned up to `day` (on the plant at the first recording or set since),
    with the days of its events so far (NaN = not (yet)): set_day (NaN for a fruit on the plant at day 0),
    red_day, harvest_day, and whether it is on the plant on `day`."""
    lives = sc.lives or {}
    ids = np.array(sorted(lives), np.int32)
    near = sc.near_by_id or {}

    def upto(v: float) -> float:
        return v if v <= day else float("nan")
    return pd.DataFrame({
        "fruit_id": ids,
        "set_day": np.array([lives[i].t0_day if lives[i].t0_day > 0 else np.nan for i in ids], np.float64),
        "red_day": np.array([upto(lives[i].t_red_day) for i in ids], np.float64),
        "harvest_day": np.array([upto(lives[i].t_harvest_day) for i in ids], np.float64),
        "present": np.array([lives[i].present(day) for i in ids], bool),
        "near_row": np.array([near[int(i)] for i in ids], bool),
    })


def fruit_table(fruits: list[scene.Fruit], n_frames_visible: np.ndarray) -> pd.DataFrame:
    """gt/fruits.parquet: the data/README.md columns plus n_frames_visible (frames with >= 1 pixel of it)."""
    centres = np.array([f.centre for f in fruits], np.float64).reshape(-1, 3)
    return pd.DataFrame({
        "fruit_id": np.array([f.fruit_id for f in fruits], np.int32),
        "class_id": np.array([f.class_id for f in fruits], np.int32),
        "x_m": centres[:, 0], "y_m": centres[:, 1], "z_m": centres[:, 2],
        "diameter_m": np.array([f.diameter_m for f in fruits], np.float64),
        "diameter_max_m": np.array([f.diameter_max_m for f in fruits], np.float64),
        "diameter_nominal_m": np.array([f.diameter_nominal_m for f in fruits], np.float64),
        "length_m": np.array([f.length_m for f in fruits], np.float64),
        "near_row": np.array([f.near_row for f in fruits], bool),
        "n_frames_visible": np.asarray(n_frames_visible, np.int32),
    })


def run(inputs: dict, cfg: Config, ctx: StageContext) -> dict[str, pd.DataFrame]:
    out = ctx.output_dir("raw")
    stamps = frame_stamps(cfg)
    odom_stamps = odometry_stamps(cfg, stamps)
    odom_t0, n_odom = int(odom_stamps[0]), len(odom_stamps)

    t_robot_camera = trajectory.camera_extrinsic(cfg.camera_mast_m, cfg.camera_lateral_m)
    k = intrinsics(cfg)
    # the row is laid out from the first day's path, so every day shows the same plants
    first = trajectory.BasePath.random(cfg.speed_m_per_s, cfg.base_height_m, 0.0, np.random.default_rng([cfg.seed, 1]))
    first_cam = first.poses((stamps - stamps[0] + 200_000_000) / 1e9) @ t_robot_camera
    layout = row_layout(cfg, first_cam[:, 0, 3], cfg.camera_lateral_m, cfg.base_height_m + cfg.camera_mast_m, k)
    path = first
    if cfg.day > 0:
        rng = stream(cfg, 1)
        path = trajectory.BasePath.random(cfg.speed_m_per_s, cfg.base_height_m,
                                          float(rng.uniform(-START_SHIFT_M, START_SHIFT_M)), rng)
    ox, oy, oyaw = path.xy_yaw((odom_stamps - odom_t0) / 1e9)
    odom = trajectory.drifting_odometry(ox, oy, oyaw, cfg.base_height_m,
                                        trajectory.OdometryErrors(cfg.odom_drift_m_per_m, cfg.odom_yaw_drift_deg_per_m,
                                                                  cfg.odom_noise_m),
                                        stream(cfg, 2))
    if cfg.day > 0:  # the robot's odometry starts at its own origin: x = y = 0 where it starts, heading kept
        odom[:, 0, 3] -= ox[0]
        odom[:, 1, 3] -= oy[0]
    cam = path.poses((stamps - odom_t0) / 1e9) @ t_robot_camera  # [N, 4, 4] true camera-to-world
    sc = scene.build_scene(layout, cfg.seed, scene.Season(cfg.day, cfg.growth_rate_scale, cfg.fruit_set_per_m_per_week))
    fruits = sc.fruits
    n_ids = max([f.fruit_id for f in fruits], default=0) + 1
    by_id = np.zeros(n_ids, bool)
    by_id[[f.fruit_id for f in fruits]] = True

    def per_id(values: list, fill) -> np.ndarray:
        out = np.full(n_ids, fill, np.asarray(values).dtype if values else type(fill))
        out[by_id] = values
        return out
    sizes = detector.FruitSizes(per_id([f.diameter_nominal_m for f in fruits], 0.0),
                                per_id([f.length_m for f in fruits], 0.0),
                                per_id([f.near_row for f in fruits], False), float(k[0, 0]), float(k[1, 1]))
    noise = detector.DetectorNoise(cfg.det_miss_rate, cfg.det_false_pos_rate, cfg.det_boundary_px,
                                   cfg.det_merge_rate, cfg.det_class_confusion_rate, cfg.det_void_rate,
                                   cfg.det_min_area_px)
    labelled = set(labelled_frames(cfg))
    workers = cfg.workers or min(4, os.cpu_count() or 1)
    rays = render.camera_rays(k, cfg.width, cfg.height, cfg.supersample)

    def render_frame(i: int) -> dict:
        """Ray-cast frame i and run the simulated detector on it (both on a worker thread; the detector's
        random stream is frame i's own, so the result does not depend on the thread). The ray cast holds the
        GIL (Open3D), so it casts on every core while the other render threads wait for it."""
        fr = render.render(sc, cam[i], k, cfg.width, cfg.height, cfg.supersample, cfg.texture_scale,
                           nthreads=os.cpu_count() or 1, rays=rays)
        fr["detections"] = detector.detect(fr["semantic"], fr["instance"], fr["depth"], sizes, noise,
                                           stream(cfg, 3, i))
        return fr

    bag = None
    if cfg.write_bag:
        bag = writers.Ros1BagWriter(out / f"{Path(ctx.seq).name}.bag", TOPICS)  # (nested SEQ: its last part)
        bag.static_tf(int(odom_stamps[0]), BASE_FRAME, CAMERA_FRAME, trajectory.to_txyzq(t_robot_camera[None])[0])
    odom_txyzq = trajectory.to_txyzq(odom)
    lin, ang = odometry_twist(odom_stamps, odom)
    next_odom = 0

    def odom_until(stamp_ns: int) -> None:
        nonlocal next_odom
        while bag is not None and next_odom < n_odom and odom_stamps[next_odom] <= stamp_ns:
            j = next_odom
            bag.odom(int(odom_stamps[j]), odom_txyzq[j], lin[j], ang[j], ODOM_FRAME, BASE_FRAME)
            next_odom += 1

    det_writer = writers.DetectorWriter(out, cfg.detections_format, cfg.width, cfg.height)
    annotated: list[tuple[int, np.ndarray, np.ndarray]] = []
    views = np.zeros(n_ids, np.int32)
    try:
        rendered = parallel.in_order(render_frame, range(cfg.n_frames), workers)
        for i, fr in enumerate(ctx.progress(rendered, "render and write", cfg.n_frames)):
            stamp = int(stamps[i])
            depth_mm = depth_to_mm(fr["depth"])
            det = fr["detections"]
            writers.write_frame_pngs(out, stamp, fr["rgb"], depth_mm, fr["semantic"], fr["instance"])
            det_writer.frame(stamp, det.semantic, det.instance, det.segments)
            for key, n in det.stats.items():
                ctx.count(f"detector_{key}", n)
            views += np.bincount(fr["instance"].ravel(), minlength=n_ids) > 0
            if i in labelled:
                annotated.append((stamp, fr["semantic"], fr["instance"]))
                write_png(out / "seg" / f"{stamp}.png", fr["instance"])
            if bag is not None:
                odom_until(stamp)
                bag.camera_info(stamp, k, cfg.width, cfg.height, CAMERA_FRAME)
                bag.image("color", stamp, fr["rgb"], "rgb8", CAMERA_FRAME)
                bag.image("depth", stamp, depth_mm, "16UC1", CAMERA_FRAME)
        odom_until(int(odom_stamps[-1]))
    finally:
        if bag is not None:
            bag.close()

    writers.write_params(out / "params.yaml", k, t_robot_camera, cfg.width, cfg.height)
    writers.write_odometry_csv(out / "odometry.csv", odom_stamps, odom_txyzq)
    det_writer.close()
    writers.write_json(out / "annotations.json", writers.coco_annotations(annotated, cfg.width, cfg.height))

    gt = out / "gt"
    gt.mkdir(exist_ok=True)
    poses = pd.DataFrame(trajectory.to_txyzq(cam), columns=writers.POSE_COLUMNS)
    poses.insert(0, "stamp_ns", stamps)
    poses.insert(0, "frame_id", np.arange(cfg.n_frames, dtype=np.int32))
    poses.to_parquet(gt / "poses.parquet", index=False)
    table = fruit_table(fruits, views[by_id])
    table.to_parquet(gt / "fruits.parquet", index=False)
    if cfg.day > 0:  # (day 0 writes exactly the files a row always had)
        season_table(sc, cfg.day).to_parquet(gt / "season.parquet", index=False)
    # the settings that made the row (render threads do not change it)
    # (the preset is left out: the resolved sizes it filled in are written)
    settings = {k_: list(v) if isinstance(v, tuple) else v for k_, v in asdict(cfg).items()
                if k_ not in ("workers", "preset") and (cfg.day > 0 or k_ not in SEASON_SETTINGS)}
    (gt / "synth_config.yaml").write_text(yaml.safe_dump(settings, sort_keys=True))

    near = table["near_row"].to_numpy()
    seen = table["n_frames_visible"].to_numpy() > 0
    ctx.count("frames", cfg.n_frames)
    ctx.count("fruits_near", int(near.sum()))
    ctx.count("fruits_near_seen", int((near & seen).sum()))
    ctx.count("fruits_far", int((~near).sum()))
    ctx.count("labelled_frames", len(annotated))
    ctx.count("odometry_samples", n_odom)
    drift = np.hypot(odom[-1, 0, 3] - ox[-1], odom[-1, 1, 3] - oy[-1])
    ctx.note(f"{cam[-1, 0, 3] - cam[0, 0, 3]:.2f} m of row in {cfg.n_frames} frames; odometry ends "
             f"{drift:.3f} m off the truth; {int((near & seen).sum())} near-row fruits in view")
    return {}
