"""Read a recorded row (ROS 1/2 bag or BUP20-style PNG folder) into the frames and detections tables."""
from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import pandas as pd

import schemas
from pipeline.classes import THING_IDS
from pipeline.images import read_label, write_png
from pipeline.stage import StageContext
from sources.common import (FrameSource, IngestError, depth_to_mm, interpolate_poses, pair_nearest, stamp_from_name,
                            txyzq_from_pose)
from sources.png_folder import PngFolder
from sources.rosbag import RosBag, Topics, is_ros2_dir

INPUTS = ("raw",)
OUTPUTS = ("frames", "detections", "images")


@dataclass(frozen=True)
class Config:
    source: Literal["auto", "png", "bag"] = "auto"
    """'png' = the BUP20-style folder, 'bag' = a ROS bag, 'auto' = png when rgb/ exists, else the bag."""
    bag_path: str = ""
    """bag inside the raw folder ('' = the only *.bag, *.mcap or ROS 2 bag directory there)."""
    color_topic: str = "/camera/color/image_raw"
    """colour image topic (sensor_msgs/Image)."""
    depth_topic: str = "/camera/aligned_depth_to_color/image_raw"
    """depth aligned to colour (sensor_msgs/Image, 16UC1 mm or 32FC1 m)."""
    camera_info_topic: str = "/camera/color/camera_info"
    """colour camera intrinsics (sensor_msgs/CameraInfo)."""
    odom_topic: str = "/odom"
    """robot odometry (nav_msgs/Odometry); if absent, odom_frame -> base_frame on tf_topic."""
    tf_topic: str = "/tf"
    """transform topic used when there is no odometry topic."""
    odom_frame: str = "odom"
    """world frame of the odometry."""
    base_frame: str = "base_link"
    """robot frame the odometry tracks."""
    camera_frame: str = "camera_color_optical_frame"
    """colour optical frame; base_frame -> camera_frame on /tf_static gives the extrinsic."""
    pair_tolerance_ms: float = 20.0
    """colour and depth images further apart than this are not paired (the frame is skipped and counted)."""
    odom_tolerance_ms: float = 100.0
    """frames beyond the odometry's ends, or in gaps longer than twice this, are skipped and counted."""
    odometry_csv: str = "odometry.csv"
    """odometry file of the PNG folder (BUP20 also has rgbd_odom.csv)."""
    detections_dir: str = "pred_seg"
    """detector output folder in the raw folder: semantic/, instance/, scores.csv."""
    annotations: str = "annotations.json"
    """COCO annotations of the labelled frames: looked for in the raw folder, then in the two folders above it
    (a BUP20 release keeps one annotation file at its root, above <date>/row<N>); images of other rows in
    a shared file simply match no frame. Without it, the stamps of seg/<stamp>.png mark the labelled frames."""
    match_tolerance_ms: float = 1.0
    """detector / annotation files match a frame when their name's stamp is this close."""
    on_bad_image: Literal["skip", "error"] = "skip"
    """a colour or depth image that cannot be decoded: skip the frame (counted) or stop with an error."""
    max_frames: int = 0
    """ingest at most this many frames (0 = all)."""


def find_bag(raw: Path, cfg: Config) -> Path:
    if cfg.bag_path:
        p = raw / cfg.bag_path
        if not p.exists():
            raise IngestError(f"ingest.bag_path {cfg.bag_path!r}: {p} does not exist")
        return p
    cands = sorted(p for p in raw.iterdir() if (p.is_file() and p.suffix in (".bag", ".mcap")) or is_ros2_dir(p))
    if not cands:
        raise IngestError(f"no bag in {raw} (looked for *.bag, *.mcap and ROS 2 bag directories with metadata.yaml)"
                          f" and no rgb/ folder; {raw} has: {sorted(p.name for p in raw.iterdir())}")
    if len(cands) > 1:
        raise IngestError(f"several bags in {raw}: {[p.name for p in cands]}; choose one with --set ingest.bag_path=NAME")
    return cands[0]


def open_source(raw: Path, cfg: Config) -> FrameSource:
    if not raw.is_dir():
        raise IngestError(f"raw folder {raw} does not exist")
    kind = cfg.source
    if kind == "auto":
        kind = "png" if (raw / "rgb").is_dir() else "bag"
    if kind == "png":
        return PngFolder(raw, cfg.odometry_csv)
    topics = Topics(cfg.color_topic, cfg.depth_topic, cfg.camera_info_topic, cfg.odom_topic, cfg.tf_topic,
                    cfg.odom_frame, cfg.base_frame, cfg.camera_frame)
    bag = find_bag(raw, cfg)
    return RosBag(bag, topics, params_fallback=raw / "params.yaml")


def index_by_stamp(folder: Path) -> tuple[np.ndarray, list[Path]]:
    files = sorted(folder.glob("*.png")) if folder.is_dir() else []
    stamps, paths = [], []
    for f in files:
        try:
            stamps.append(stamp_from_name(f.stem))
            paths.append(f)
        except IngestError:
            continue
    order = np.argsort(stamps)
    return np.array(stamps, np.int64)[order], [paths[i] for i in order]


def match(frame_stamps: np.ndarray, stamps: np.ndarray, tol_ns: int) -> np.ndarray:
    return pair_nearest(frame_stamps, stamps, tol_ns) if len(stamps) else np.full(len(frame_stamps), -1)


def find_annotations(raw: Path, name: str) -> Path | None:
    """`name` in the row folder, else in its parent, else in the folder above that (the BUP20 release root of
    <root>/<date>/row<N>); the row folder may be a symbolic link into the release."""
    real = raw.resolve()
    for folder in (raw, real.parent, real.parent.parent):
        if (folder / name).is_file():
            return folder / name
    return None


def labelled_stamps(raw: Path, cfg: Config) -> np.ndarray:
    path = find_annotations(raw, cfg.annotations)
    if path is not None:
        try:
            ann = json.loads(path.read_text())
            names = [Path(img["file_name"]).stem for img in ann["images"]]
        except (json.JSONDecodeError, KeyError, TypeError) as err:
            raise IngestError(f"{path}: not COCO annotations with images[].file_name: {err}") from err
        return np.array(sorted(stamp_from_name(n) for n in names), np.int64)
    return index_by_stamp(raw / "seg")[0]


def read_scores(path: Path) -> pd.DataFrame:
    cols = ["stamp_ns", "segment_id", "class_id", "score"]
    if not path.is_file():
        return pd.DataFrame(columns=cols)
    df = pd.read_csv(path)
    missing = [c for c in cols if c not in df.columns]
    if missing:
        raise IngestError(f"{path}: columns {missing} missing; columns present: {list(df.columns)}")
    return df[cols]


def rel(path: Path, data_root: Path) -> str:
    return Path(os.path.relpath(path.resolve(), data_root.resolve())).as_posix()


def run(inputs: dict, cfg: Config, ctx: StageContext) -> dict[str, pd.DataFrame]:
    raw: Path = inputs["raw"]
    src = open_source(raw, cfg)
    rec = src.recording
    for k, v in rec.counts.items():
        ctx.count(k, v)
    cs = rec.color_stamps
    di = pair_nearest(cs, rec.depth_stamps, int(cfg.pair_tolerance_ms * 1e6))
    poses_base, odom_ok = interpolate_poses(rec.odometry, cs, int(cfg.odom_tolerance_ms * 1e6))
    keep = (di >= 0) & odom_ok
    ctx.count("skipped_no_depth", int((di < 0).sum()))
    ctx.count("skipped_no_odometry", int(((di >= 0) & ~odom_ok).sum()))
    idx = np.flatnonzero(keep)
    if cfg.max_frames:
        idx = idx[: cfg.max_frames]
    if len(idx) == 0:
        raise IngestError(f"{src.describe()}: no frame has both a depth image within {cfg.pair_tolerance_ms} ms "
                          f"and odometry within {cfg.odom_tolerance_ms} ms ({len(cs)} colour, "
                          f"{len(rec.depth_stamps)} depth images, odometry {rec.odometry.stamps_ns[0]}.."
                          f"{rec.odometry.stamps_ns[-1]} ns, colour {cs[0]}..{cs[-1]} ns)")
    cam_poses = poses_base @ rec.t_robot_camera
    out_dir = ctx.output_dir("images")
    decoded: dict[int, tuple[str, str, float]] = {}
    pairs = [(int(i), int(di[i])) for i in idx]
    for ci, rgb, depth, err in ctx.progress(src.frames(pairs), "frames", len(pairs)):
        if err:
            if cfg.on_bad_image == "error":
                raise IngestError(err)
            ctx.count("skipped_bad_image")
            ctx.note(f"skipped frame at {cs[ci]} ns: {err}")
            continue
        h, w = rgb.shape[:2]
        rec.camera.check(w, h, f"colour image at {cs[ci]} ns")
        if depth.shape != (h, w):
            raise IngestError(f"frame at {cs[ci]} ns: depth is {depth.shape[1]}x{depth.shape[0]} but colour is "
                              f"{w}x{h}; depth must be aligned to colour")
        mm = depth_to_mm(depth)
        valid = float((mm > 0).mean())
        if valid == 0:
            ctx.count("frames_without_valid_depth")
        name = f"{cs[ci]}.png"
        write_png(out_dir / "rgb" / name, rgb)
        write_png(out_dir / "depth" / name, mm)
        decoded[ci] = (ctx.relpath("images", f"rgb/{name}"), ctx.relpath("images", f"depth/{name}"), valid)
    order = [i for i in idx if i in decoded]
    if not order:
        raise IngestError(f"{src.describe()}: no frame could be decoded")
    stamps = cs[order]
    tol = int(cfg.match_tolerance_ms * 1e6)
    det_dir = raw / cfg.detections_dir
    sem_st, sem_files = index_by_stamp(det_dir / "semantic")
    ins_st, ins_files = index_by_stamp(det_dir / "instance")
    gts_st, gts_files = index_by_stamp(raw / "gt" / "semantic")
    gti_st, gti_files = index_by_stamp(raw / "gt" / "instance")
    m_sem, m_ins = match(stamps, sem_st, tol), match(stamps, ins_st, tol)
    m_gts, m_gti = match(stamps, gts_st, tol), match(stamps, gti_st, tol)
    lab = labelled_stamps(raw, cfg)
    is_lab = match(stamps, lab, tol) >= 0
    txyzq = txyzq_from_pose(cam_poses[order])
    k = rec.camera.k
    root = ctx.data_root
    frames = pd.DataFrame({
        "frame_id": np.arange(len(order), dtype=np.int32), "stamp_ns": stamps,
        "depth_stamp_ns": rec.depth_stamps[di[order]], "width": rec.camera.width, "height": rec.camera.height,
        "fx": k[0, 0], "fy": k[1, 1], "cx": k[0, 2], "cy": k[1, 2],
        **{c: txyzq[:, j] for j, c in enumerate(["tx", "ty", "tz", "qx", "qy", "qz", "qw"])},
        "rgb_path": [decoded[i][0] for i in order], "depth_path": [decoded[i][1] for i in order],
        "depth_scale_m": 0.001, "valid_depth_frac": [decoded[i][2] for i in order], "labelled": is_lab,
        "det_semantic_path": [rel(sem_files[j], root) if j >= 0 and m_ins[n] >= 0 else None
                              for n, j in enumerate(m_sem)],
        "det_instance_path": [rel(ins_files[j], root) if j >= 0 and m_sem[n] >= 0 else None
                              for n, j in enumerate(m_ins)],
        "gt_semantic_path": [rel(gts_files[j], root) if j >= 0 and m_gti[n] >= 0 else None
                             for n, j in enumerate(m_gts)],
        "gt_instance_path": [rel(gti_files[j], root) if j >= 0 and m_gts[n] >= 0 else None
                             for n, j in enumerate(m_gti)],
    })
    no_det = int(frames["det_instance_path"].isna().sum())
    if no_det:
        ctx.count("frames_without_detections", no_det)
    detections = read_detections(frames, raw / cfg.detections_dir / "scores.csv", ins_st, tol, ctx)
    ctx.summary.update(frames=len(frames), labelled=int(is_lab.sum()), segments=len(detections),
                       source=src.describe())
    return {"frames": frames, "detections": detections}


def read_detections(frames: pd.DataFrame, scores_path: Path, ins_stamps: np.ndarray, tol: int,
                    ctx: StageContext) -> pd.DataFrame:
    """One row per segment: scores.csv rows matched to frames, areas from the instance PNGs."""
    scores = read_scores(scores_path)
    if len(scores):
        sst = scores["stamp_ns"].to_numpy(np.int64)
        uniq = np.unique(sst)
        frame_of = dict(zip(uniq, match(uniq, frames["stamp_ns"].to_numpy(np.int64), tol)))
        scores = scores.assign(frame_row=[frame_of[s] for s in sst])
        by_frame = {k: g for k, g in scores[scores.frame_row >= 0].groupby("frame_row")}
    else:
        by_frame = {}
        if len(ins_stamps):
            ctx.note(f"{scores_path} missing: segments taken from the instance PNGs with score 1.0")
    rows = []
    for n, fr in enumerate(frames.itertuples(index=False)):
        if not isinstance(fr.det_instance_path, str):  # None, or NaN in a string column
            continue
        inst = read_label(ctx.abspath(fr.det_instance_path), "detector instance")
        sem = read_label(ctx.abspath(fr.det_semantic_path), "detector semantic")
        if inst.shape != (fr.height, fr.width) or sem.shape != inst.shape:
            raise IngestError(f"detector PNGs {fr.det_instance_path} / {fr.det_semantic_path} are "
                              f"{inst.shape} / {sem.shape}; the frame is {fr.height}x{fr.width}")
        area = np.bincount(inst.ravel())
        present = set(np.flatnonzero(area[1:]) + 1)
        listed = by_frame.get(n)
        seen = set()
        if listed is not None:
            for s in listed.itertuples(index=False):
                sid = int(s.segment_id)
                a = int(area[sid]) if sid < len(area) else 0
                if a == 0:
                    ctx.count("segments_missing_in_png")
                score = float(s.score) if np.isfinite(s.score) else 0.0
                rows.append((fr.frame_id, sid, int(s.class_id), min(max(score, 0.0), 1.0), a))
                seen.add(sid)
        for sid in sorted(present - seen):
            klass = int(np.bincount(sem[inst == sid]).argmax())
            if klass not in THING_IDS:
                continue
            if listed is not None:
                ctx.count("segments_without_score")
            rows.append((fr.frame_id, int(sid), klass, 1.0 if listed is None else 0.5, int(area[sid])))
    if not rows:
        return schemas.empty("detections")
    df = pd.DataFrame(rows, columns=["frame_id", "segment_id", "class_id", "score", "area_px"])
    return df.assign(near_depth_frac=np.nan, kept=True, drop_reason="")
