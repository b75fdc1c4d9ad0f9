"""Generate the synthetic glasshouse row, with exact ground truth, in the formats a real recording has."""
from __future__ import annotations

import os
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass

import multiprocessing as mp
import numpy as np
import pandas as pd
import yaml

from pipeline.stage import StageContext
from synthetic import detector, scene, trajectory, writers

INPUTS: tuple[str, ...] = ()
OUTPUTS = ("raw",)

T0_NS = 1_600_000_000_000_000_000


@dataclass(frozen=True)
class Config:
    seed: int = 0
    """random seed: every knob below changes the row deterministically for a given seed."""
    n_frames: int = 120
    """camera frames in the row."""
    width: int = 320
    """image width in pixels."""
    height: int = 180
    """image height in pixels."""
    fov_x_deg: float = 69.0
    """horizontal field of view (RealSense D435 colour: 69 deg)."""
    fps: float = 15.0
    """camera frame rate."""
    speed_m_per_s: float = 0.2
    """robot speed along the row."""
    camera_height_m: float = 0.7
    """camera height above the floor."""
    camera_distance_m: float = 0.5
    """distance from the camera to the near row's plant line."""
    far_row_distance_m: float = 1.9
    """distance from the camera to the far row (beyond the 1.5 m depth filter)."""
    fruits_per_m: float = 12.0
    """fruits per metre of row (near and far rows alike)."""
    odom_drift_m_per_m: float = 0.03
    """odometry scale error: accumulated position error per metre travelled."""
    odom_yaw_drift_deg_per_m: float = 2.0
    """odometry heading drift per metre travelled."""
    odom_noise_m: float = 0.002
    """odometry random-walk noise, metres per sqrt(metre) travelled."""
    odom_rate_hz: float = 50.0
    """odometry message rate."""
    det_miss_rate: float = 0.15
    """share of visible fruits the detector misses (more for small, occluded ones)."""
    det_false_pos_rate: float = 0.3
    """expected false-positive fruit segments per frame."""
    det_boundary_px: int = 2
    """detected masks are eroded or dilated by up to this many pixels."""
    det_merge_rate: float = 0.05
    """chance that a detected fruit is merged with a touching neighbour."""
    det_class_confusion_rate: float = 0.05
    """chance that a detected fruit gets a neighbouring ripeness class."""
    n_labelled: int = 3
    """sparse labelled frames (ground-truth annotations), spread along the row."""
    supersample: int = 2
    """anti-aliasing: rays per pixel side for the colour image."""
    write_bag: bool = True
    """also write the recording as a ROS 1 bag <SEQ>.bag."""
    workers: int = 0
    """render processes (0 = one per CPU core, at most 4)."""

    def __post_init__(self) -> None:
        for name in ("n_frames", "width", "height", "n_labelled", "supersample"):
            if getattr(self, name) < (1 if name != "n_labelled" else 0):
                raise ValueError(f"synth.{name} must be positive, got {getattr(self, name)}")
        for name in ("det_miss_rate", "det_merge_rate", "det_class_confusion_rate"):
            if not 0 <= getattr(self, name) <= 1:
                raise ValueError(f"synth.{name} must be in [0, 1], got {getattr(self, name)}")
        if not 0 < self.fov_x_deg < 170:
            raise ValueError(f"synth.fov_x_deg must be in (0, 170), got {self.fov_x_deg}")
        if self.n_labelled > self.n_frames:
            raise ValueError(f"synth.n_labelled ({self.n_labelled}) exceeds n_frames ({self.n_frames})")


def layout_for(cfg: Config, travel_m: float) -> scene.RowLayout:
    lateral = 0.1  # camera offset from base_link towards the plants
    pad = 1.6      # the far row is seen over a wider stretch than the near row
    return scene.RowLayout(x_min_m=-pad, x_max_m=travel_m + pad, near_row_y_m=lateral + cfg.camera_distance_m,
                           far_row_y_m=lateral + cfg.far_row_distance_m,
                           wall_y_m=lateral + cfg.far_row_distance_m + 1.0,
                           fruit_z_range_m=(cfg.camera_height_m - 0.2, cfg.camera_height_m + 0.18),
                           plant_spacing_m=0.3, fruits_per_m=cfg.fruits_per_m)


def intrinsics(cfg: Config) -> np.ndarray:
    fx = cfg.width / 2 / np.tan(np.radians(cfg.fov_x_deg) / 2)
    return np.array([[fx, 0, cfg.width / 2], [0, fx, cfg.height / 2], [0, 0, 1.0]])


def _render_chunk(args: tuple) -> list[dict]:
    layout, seed, poses, k, w, h, ss = args
    sc = scene.build_scene(layout, seed)
    return [scene.render(sc, p, k[0, 0], k[1, 1], k[0, 2], k[1, 2], w, h, ss) for p in poses]


def render_all(cfg: Config, layout: scene.RowLayout, poses: np.ndarray, k: np.ndarray, ctx: StageContext) -> list[dict]:
    n_workers = cfg.workers or min(4, os.cpu_count() or 1)
    chunk = max(1, min(8, len(poses) // max(1, n_workers * 2)))
    jobs = [(layout, cfg.seed, poses[i:i + chunk], k, cfg.width, cfg.height, cfg.supersample)
            for i in range(0, len(poses), chunk)]
    if n_workers == 1:
        return [f for j in ctx.progress(jobs, "render", len(jobs)) for f in _render_chunk(j)]
    with ProcessPoolExecutor(n_workers, mp_context=mp.get_context("spawn")) as pool:
        return [f for part in ctx.progress(pool.map(_render_chunk, jobs), "render", len(jobs)) for f in part]


def run(inputs: dict, cfg: Config, ctx: StageContext) -> dict[str, pd.DataFrame]:
    out = ctx.output_dir("raw")
    rng = np.random.default_rng(cfg.seed)
    period_ns = int(round(1e9 / cfg.fps))
    first_ns = T0_NS + 200_000_000
    stamps = first_ns + np.arange(cfg.n_frames, dtype=np.int64) * period_ns
    duration_s = (stamps[-1] - T0_NS) / 1e9 + 0.2
    travel = cfg.speed_m_per_s * duration_s
    layout = layout_for(cfg, travel)
    traj = trajectory.make_trajectories(T0_NS, duration_s, cfg.odom_rate_hz, cfg.speed_m_per_s, 0.0,
                                        cfg.odom_drift_m_per_m, cfg.odom_yaw_drift_deg_per_m, cfg.odom_noise_m,
                                        np.random.default_rng([cfg.seed, 1]))
    t_rc = trajectory.camera_extrinsic(cfg.camera_height_m)
    cam_gt = trajectory.interpolate(traj.stamps_ns, traj.gt_base, stamps) @ t_rc
    k = intrinsics(cfg)

    frames = render_all(cfg, layout, cam_gt, k, ctx)
    sc = scene.build_scene(layout, cfg.seed)  # for the fruit table (same seed, same scene)

    noise = detector.DetectorNoise(cfg.det_miss_rate, cfg.det_false_pos_rate, cfg.det_boundary_px,
                                   cfg.det_merge_rate, cfg.det_class_confusion_rate)
    fruit_px = k[0, 0] * 0.075 / cfg.camera_distance_m
    labelled_idx = set(np.round(np.linspace(0, cfg.n_frames - 1, cfg.n_labelled + 2)[1:-1]).astype(int).tolist()) \
        if cfg.n_labelled else set()
    score_rows, labelled = [], []
    bag = None
    if cfg.write_bag:
        bag = writers.Ros1BagWriter(out / f"{ctx.seq}.bag", "/camera/color/image_raw",
                                    "/camera/aligned_depth_to_color/image_raw", "/camera/color/camera_info", "/odom")
        bag.static_tf(T0_NS, "base_link", "camera_color_optical_frame", trajectory.to_txyzq(t_rc[None])[0])
    odom_txyzq = trajectory.to_txyzq(traj.odom_base)
    odom_iter = iter(range(len(traj.stamps_ns)))
    next_odom = next(odom_iter, None)
    for i in ctx.progress(range(cfg.n_frames), "write", cfg.n_frames):
        fr, stamp = frames[i], int(stamps[i])
        det = detector.corrupt(fr["semantic"], fr["instance"], noise, np.random.default_rng([cfg.seed, 2, i]),
                               fruit_px)
        writers.write_frame_pngs(out, stamp, fr, det)
        score_rows += [(stamp, sid, klass, score) for sid, klass, score in det[2]]
        if i in labelled_idx:
            labelled.append((stamp, fr["semantic"], fr["instance"]))
            writers.write_png(out / "seg" / f"{stamp}.png", fr["instance"])
        if bag is not None:
            while next_odom is not None and traj.stamps_ns[next_odom] <= stamp:
                bag.odom(int(traj.stamps_ns[next_odom]), odom_txyzq[next_odom])
                next_odom = next(odom_iter, None)
            bag.camera_info(stamp, k, cfg.width, cfg.height, "camera_color_optical_frame")
            bag.image("color", stamp, fr["rgb"], "rgb8", "camera_color_optical_frame")
            bag.image("depth", stamp, writers.depth_to_mm(fr["depth"]), "16UC1", "camera_color_optical_frame")
    if bag is not None:
        while next_odom is not None:
            bag.odom(int(traj.stamps_ns[next_odom]), odom_txyzq[next_odom])
            next_odom = next(odom_iter, None)
        bag.close()

    writers.write_params(out / "params.yaml", k, t_rc, cfg.width, cfg.height)
    writers.write_odometry_csv(out / "odometry.csv", traj.stamps_ns, odom_txyzq)
    pd.DataFrame(score_rows, columns=["stamp_ns", "segment_id", "class_id", "score"]).to_csv(
        out / "pred_seg" / "scores.csv", index=False)
    writers.write_json(out / "annotations.json", writers.coco_annotations(labelled, cfg.width, cfg.height))

    gt_dir = out / "gt"
    poses = pd.DataFrame(trajectory.to_txyzq(cam_gt), columns=["tx", "ty", "tz", "qx", "qy", "qz", "qw"])
    poses.insert(0, "stamp_ns", stamps)
    poses.insert(0, "frame_id", np.arange(cfg.n_frames, dtype=np.int32))
    poses.to_parquet(gt_dir / "poses.parquet", index=False)
    fruits = pd.DataFrame([{"fruit_id": f.fruit_id, "class_id": f.class_id, "x_m": f.centre[0], "y_m": f.centre[1],
                            "z_m": f.centre[2], "diameter_m": f.diameter_m, "length_m": f.length_m,
                            "near_row": f.near_row} for f in sc.fruits])
    fruits.to_parquet(gt_dir / "fruits.parquet", index=False)
    (gt_dir / "synth_config.yaml").write_text(yaml.safe_dump(asdict(cfg), sort_keys=True))
    ctx.summary.update(frames=cfg.n_frames, fruits_near=int(fruits["near_row"].sum()),
                       fruits_far=int((~fruits["near_row"]).sum()), detections=len(score_rows),
                       labelled=len(labelled), travel_m=round(float(travel), 3))
    return {}
