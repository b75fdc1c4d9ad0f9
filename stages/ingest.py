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
from pipeline.classes import DEFAULT_CLASSES, THING_IDS, VOID
from pipeline.images import ImageError, read_label, write_png
from pipeline.parallel import available_cores, in_order
from pipeline.stage import StageContext
from sources.common import (FrameSource, IngestError, StampUnit, depth_to_mm, interpolate_poses, pair_nearest,
                            stamp_from_name, txyzq_from_pose)
from sources.detections import (ClassMapper, CocoInstances, CocoPanoptic, UnreadableLabels, detect_format,
                                load_class_map, match_stamps)
from sources.png_folder import PngFolder
from sources.rosbag import RosBag, Topics, is_ros2_dir

INPUTS = ("raw",)
OUTPUTS = ("frames", "detections", "input_checks", "images")


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
    stamp_unit: Literal["auto", "ns", "us", "ms", "s"] = "auto"
    """unit of the stamps in file names and odometry.csv: ns, us, ms, s, or 'auto' = only names whose digits leave
    no doubt, else an error (data/README.md, Timestamps); set it for a clock counting from boot."""
    detections_dir: str = "pred_seg"
    """detector output folder in the raw folder (see docs/detector_formats.md)."""
    detections_format: Literal["auto", "png_pair", "coco_panoptic", "coco_instances"] = "auto"
    """format of the detector output: 'png_pair' = semantic/ + instance/ PNGs + scores.csv; 'coco_panoptic' =
    a Detectron2 / Mask2Former panoptic JSON + its PNG folder; 'coco_instances' = a COCO results JSON (RLE or
    polygon masks, optional semantic/ PNGs for the stuff); 'auto' = recognise it from the files present (the
    stage summary says which)."""
    detections_json: str = ""
    """the COCO detections JSON inside detections_dir ('' = the only *.json there besides images.json); set it
    when the folder holds several."""
    class_map: dict | str = ""
    """detector category (id or name) -> project class (id or name, or void), inline ({7: fruit_red, leaf:
    plant}) or a YAML file (relative paths are read from the raw folder). '' = the detector's category ids
    are the project's class ids (pipeline/classes.py)."""
    unmapped: Literal["error", "void"] = "error"
    """a detector category the class map does not cover: stop with an error listing them ('error'), or make
    its pixels unlabelled (void, 255) and drop its segments ('void'); how many were voided is counted."""
    annotations: str = "annotations.json"
    """COCO annotations of the labelled frames: looked for in the raw folder, then in the two folders above it
    (a BUP20 release keeps one annotation file at its root, above <date>/row<N>); images of other rows in
    a shared file simply match no frame. Without it, the stamps of seg/<stamp>.png mark the labelled frames."""
    min_frame_gap_ms: float = 1.0
    """a colour frame less than this after the previous one is a duplicate (a re-sent or twice-saved image):
    skipped and counted. Keep it well under the frame period (66 ms at 15 fps)."""
    match_tolerance_ms: float = 1.0
    """detector / annotation files match a frame when their name's stamp is this close."""
    on_bad_image: Literal["skip", "error"] = "skip"
    """a colour, depth or detector image that is missing or cannot be decoded: skip the frame (its detections
    only, for a detector image; counted and named in the summary) or stop with an error."""
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
        return PngFolder(raw, cfg.odometry_csv, cfg.stamp_unit)
    topics = Topics(cfg.color_topic, cfg.depth_topic, cfg.camera_info_topic, cfg.odom_topic, cfg.tf_topic,
                    cfg.odom_frame, cfg.base_frame, cfg.camera_frame)
    bag = find_bag(raw, cfg)
    return RosBag(bag, topics, params_fallback=raw / "params.yaml")


def duplicate_frames(stamps: np.ndarray, min_gap_ns: int) -> np.ndarray:
    """[N] bool: frames less than min_gap_ns after the last kept frame (sorted stamps)."""
    dup = np.zeros(len(stamps), bool)
    last = None
    for i, s in enumerate(stamps):
        if last is not None and s - last < min_gap_ns:
            dup[i] = True
        else:
            last = s
    return dup


def depth_used_twice(cs: np.ndarray, ds: np.ndarray, di: np.ndarray) -> np.ndarray:
    """[N] bool: colour frames whose depth image is nearer to another colour frame (each depth image pairs
    one colour frame; ties go to the earlier frame)."""
    out = np.zeros(len(cs), bool)
    best: dict[int, int] = {}
    for i in np.flatnonzero(di >= 0):
        d = int(di[i])
        if d in best and abs(int(cs[best[d]]) - int(ds[d])) <= abs(int(cs[i]) - int(ds[d])):
            out[i] = True
            continue
        if d in best:
            out[best[d]] = True
        best[d] = int(i)
    return out


def index_by_stamp(folder: Path, stamp_unit: StampUnit = "auto") -> tuple[np.ndarray, list[Path]]:
    """Sorted stamps and files of the PNGs in `folder` named by stamp (others are not this folder's)."""
    files = sorted(folder.glob("*.png")) if folder.is_dir() else []
    stamps, paths = [], []
    for f in files:
        try:
            stamps.append(stamp_from_name(f.stem, stamp_unit))
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


def labelled_stamps(raw: Path, cfg: Config, ctx: StageContext) -> np.ndarray:
    """Stamps of the labelled frames (annotations.json images, else seg/ PNG names). An annotation's
    category must be a project class or one of the file's own categories; a file with categories of its
    own (a dataset's labels) is counted and only tells which frames are labelled."""
    path = find_annotations(raw, cfg.annotations)
    if path is not None:
        try:
            ann = json.loads(path.read_text())
            names = [Path(img["file_name"]).stem for img in ann["images"]]
            anns = ann.get("annotations", [])
            used = [(a.get("id"), a.get("image_id"), a["category_id"]) for a in anns]
            own = {c["id"] for c in ann.get("categories", [])}
        except (json.JSONDecodeError, KeyError, TypeError, AttributeError, UnicodeDecodeError) as err:
            raise IngestError(f"{path}: not COCO annotations with images[].file_name and annotations[]."
                              f"category_id: {err}") from err
        classes = {c.id for c in DEFAULT_CLASSES}
        bad = [(i, img, c) for i, img, c in used if c not in classes and c not in own]
        if bad:
            i, img, c = bad[0]
            raise IngestError(f"{path}: annotation id {i} (image_id {img}) has category_id {c!r}, which neither the "
                              f"class table nor the file's categories {sorted(own)} have ({len(bad)} such "
                              f"annotation(s)); classes: {', '.join(f'{k.id}={k.name}' for k in DEFAULT_CLASSES)}")
        foreign = sorted({c for _, _, c in used if c not in classes})
        if foreign:
            ctx.count("annotation_categories_not_in_class_table", len(foreign))
            ctx.note(f"{path} uses categories {foreign} that the class table lacks; it is read only for which "
                     f"frames are labelled (ground truth comes from gt/ or seg/)")
        try:
            return np.array(sorted(stamp_from_name(n, cfg.stamp_unit) for n in names), np.int64)
        except IngestError as err:
            raise IngestError(f"{path}: images[].file_name must be named by the frame's stamp "
                              f"(rgb/<stamp_ns>.png): {err}") from None
    return index_by_stamp(raw / "seg", cfg.stamp_unit)[0]


def read_scores(path: Path) -> pd.DataFrame:
    cols = ["stamp_ns", "segment_id", "class_id", "score"]
    if not path.is_file():
        return pd.DataFrame(columns=cols)
    try:
        df = pd.read_csv(path)
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as err:
        raise IngestError(f"{path} is not a readable CSV: {err}") from err
    missing = [c for c in cols if c not in df.columns]
    if missing:
        raise IngestError(f"{path}: columns {missing} missing; columns present: {list(df.columns)}")
    df = df[cols]
    for c in cols[:3]:
        num = pd.to_numeric(df[c], errors="coerce")
        bad = num.isna() | (num != num.round())
        if bad.any():
            n = int(np.flatnonzero(bad.to_numpy())[0])
            raise IngestError(f"{path}, data row {n + 1}: {c} = {df[c].iloc[n]!r} is not an integer")
        df = df.assign(**{c: num.astype(np.int64)})
    return df.assign(score=pd.to_numeric(df["score"], errors="coerce"))


def rel(path: Path, data_root: Path) -> str:
    return Path(os.path.relpath(path.resolve(), data_root.resolve())).as_posix()


def run(inputs: dict, cfg: Config, ctx: StageContext) -> dict[str, pd.DataFrame]:
    raw: Path = inputs["raw"]
    src = open_source(raw, cfg)
    rec = src.recording
    for k, v in rec.counts.items():
        ctx.count(k, v)
    for note in rec.notes:
        ctx.note(note)
    cs = rec.color_stamps
    dup = duplicate_frames(cs, int(cfg.min_frame_gap_ms * 1e6))
    if dup.any():
        ctx.count("skipped_duplicate_frame", int(dup.sum()))
        ctx.note(f"{int(dup.sum())} colour frame(s) less than {cfg.min_frame_gap_ms} ms after the previous one "
                 f"skipped as duplicates (first at {cs[np.flatnonzero(dup)[0]]} ns)")
    di = pair_nearest(cs, rec.depth_stamps, int(cfg.pair_tolerance_ms * 1e6))
    di[dup] = -2
    shared = depth_used_twice(cs, rec.depth_stamps, di)
    if shared.any():
        ctx.count("skipped_depth_paired_with_another_frame", int(shared.sum()))
        di[shared] = -2
    poses_base, odom_ok = interpolate_poses(rec.odometry, cs, int(cfg.odom_tolerance_ms * 1e6))
    keep = (di >= 0) & odom_ok
    ctx.count("skipped_no_depth", int((di == -1).sum()))
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
    first_error = ""

    def png_name(ci: int) -> str:
        return f"{cs[ci]}.png"

    def store(item: tuple) -> tuple[int, str, float]:
        """Check and write one decoded frame (on a worker thread): (colour index, decode error, share of valid
        depth pixels)."""
        ci, rgb, depth, err = item
        if err:
            return ci, err, 0.0
        h, w = rgb.shape[:2]
        rec.camera.check(w, h, f"colour image at {cs[ci]} ns")
        if depth.shape != (h, w):
            raise IngestError(f"frame at {cs[ci]} ns ({src.where(ci, int(di[ci]))}): depth is {depth.shape[1]}x"
                              f"{depth.shape[0]} but colour is {w}x{h}; depth must be aligned to colour (RealSense: "
                              f"the aligned_depth_to_color stream)")
        mm = depth_to_mm(depth)
        write_png(out_dir / "rgb" / png_name(ci), rgb)
        write_png(out_dir / "depth" / png_name(ci), mm)
        return ci, "", float((mm > 0).mean())

    # frames are decoded in the source's order on this thread and encoded on every core
    stored = in_order(store, src.frames(pairs), available_cores())
    for ci, err, valid in ctx.progress(stored, "frames", len(pairs)):
        if err:
            if cfg.on_bad_image == "error":
                raise IngestError(err)
            first_error = first_error or err
            note_capped(ctx, "skipped_bad_image", f"skipped frame at {cs[ci]} ns: {err}")
            continue
        if valid == 0:
            ctx.count("frames_without_valid_depth")
        decoded[ci] = (ctx.relpath("images", f"rgb/{png_name(ci)}"), ctx.relpath("images", f"depth/{png_name(ci)}"),
                       valid)
    order = [i for i in idx if i in decoded]
    if not order:
        raise IngestError(f"{src.describe()}: none of the {len(pairs)} paired frames could be decoded; the first "
                          f"error: {first_error}")
    stamps = cs[order]
    tol = int(cfg.match_tolerance_ms * 1e6)
    gts_st, gts_files = index_by_stamp(raw / "gt" / "semantic", cfg.stamp_unit)
    gti_st, gti_files = index_by_stamp(raw / "gt" / "instance", cfg.stamp_unit)
    m_gts, m_gti = match(stamps, gts_st, tol), match(stamps, gti_st, tol)
    lab = labelled_stamps(raw, cfg, ctx)
    is_lab = match(stamps, lab, tol) >= 0
    lost = lab[match(lab, stamps, tol) < 0]
    if len(lost):
        ctx.count("labelled_frames_not_ingested", len(lost))
        ctx.note(f"{len(lost)} labelled frame(s) were skipped or do not exist (first at {lost[0]} ns): no window is "
                 f"centred on them and they are not evaluated")
    h, w = rec.camera.height, rec.camera.width
    det_sem, det_ins, detections = read_detector_output(raw, stamps, (h, w), cfg, ctx)
    txyzq = txyzq_from_pose(cam_poses[order])
    k = rec.camera.k
    root = ctx.data_root
    frames = pd.DataFrame({
        "frame_id": np.arange(len(order), dtype=np.int32), "stamp_ns": stamps,
        "depth_stamp_ns": rec.depth_stamps[di[order]], "width": w, "height": h,
        "fx": k[0, 0], "fy": k[1, 1], "cx": k[0, 2], "cy": k[1, 2],
        **{c: txyzq[:, j] for j, c in enumerate(["tx", "ty", "tz", "qx", "qy", "qz", "qw"])},
        "rgb_path": [decoded[i][0] for i in order], "depth_path": [decoded[i][1] for i in order],
        "depth_scale_m": 0.001, "valid_depth_frac": [decoded[i][2] for i in order], "labelled": is_lab,
        "det_semantic_path": pd.Series(det_sem, dtype=object),
        "det_instance_path": pd.Series(det_ins, dtype=object),
        "gt_semantic_path": pd.Series([rel(gts_files[j], root) if j >= 0 and m_gti[n] >= 0 else None
                                       for n, j in enumerate(m_gts)], dtype=object),
        "gt_instance_path": pd.Series([rel(gti_files[j], root) if j >= 0 and m_gts[n] >= 0 else None
                                       for n, j in enumerate(m_gti)], dtype=object),
    })
    no_det = int(frames["det_instance_path"].isna().sum())
    if no_det:
        ctx.count("frames_without_detections", no_det)
    ctx.summary.update(frames=len(frames), labelled=int(is_lab.sum()), segments=len(detections),
                       source=src.describe())
    if len(detections) == 0:
        ctx.note(f"no detector segments in the whole row (detections format: {ctx.summary['detections_format']}); "
                 f"the panoptic outputs will hold no fruit")
    return {"frames": frames, "detections": detections, "input_checks": input_checks(ctx.summary)}


def input_checks(summary: dict) -> pd.DataFrame:
    """The stage summary as a table (counts, named values, notes), for the report."""
    rows = []
    for key, value in summary.items():
        if key == "notes":
            rows += [("note", None, str(n)) for n in value]
        elif isinstance(value, (int, np.integer)) and not isinstance(value, bool):
            rows.append((key, int(value), ""))
        else:
            rows.append((key, None, str(value)))
    return pd.DataFrame(rows, columns=["check", "count", "note"]).astype({"count": "Int64"})


def read_detector_output(raw: Path, stamps: np.ndarray, shape: tuple[int, int], cfg: Config,
                         ctx: StageContext) -> tuple[list[str | None], list[str | None], pd.DataFrame]:
    """Per frame the detector semantic and instance PNG paths (relative to data/, None = no detections)
    and the detections table, from whichever format the detector folder holds."""
    det_dir = raw / cfg.detections_dir
    fmt, json_path, obj = detect_format(det_dir, cfg.detections_format, cfg.detections_json)
    ctx.summary["detections_format"] = fmt or "none"
    if not fmt:
        ctx.note(f"no detector output in {det_dir} (looked for semantic/ + instance/ PNGs or a COCO JSON)")
        return [None] * len(stamps), [None] * len(stamps), schemas.empty("detections")
    if fmt == "png_pair":
        mapping, origin = load_class_map(cfg.class_map, raw)
        cmap = ClassMapper(mapping, origin, {}, cfg.unmapped, f"{det_dir} (semantic/ and scores.csv)") \
            if mapping is not None else None
        return read_png_pair(det_dir, stamps, shape, cfg, ctx, cmap)
    return read_coco(raw, det_dir, fmt, json_path, obj, stamps, shape, cfg, ctx)


def note_capped(ctx: StageContext, key: str, msg: str, cap: int = 5) -> None:
    """Count under `key` and note the first `cap` cases (the count says how many there were)."""
    ctx.count(key)
    if ctx.summary[key] <= cap:
        ctx.note(msg)


def read_png_pair(det_dir: Path, stamps: np.ndarray, shape: tuple[int, int], cfg: Config, ctx: StageContext,
                  cmap: ClassMapper | None = None) -> tuple[list[str | None], list[str | None], pd.DataFrame]:
    """The project's PNG pair. Without a class map the frames table points at the PNGs in the raw folder;
    with one, the mapped label images are written under images/det/ (segments mapped to stuff removed)."""
    tol = int(cfg.match_tolerance_ms * 1e6)
    root = ctx.data_root
    sem_st, sem_files = index_by_stamp(det_dir / "semantic", cfg.stamp_unit)
    ins_st, ins_files = index_by_stamp(det_dir / "instance", cfg.stamp_unit)
    m_sem, m_ins = match(stamps, sem_st, tol), match(stamps, ins_st, tol)
    sem_paths: list[Path | None] = []
    ins_paths: list[Path | None] = []
    for n, (a, b) in enumerate(zip(m_sem, m_ins)):
        if (a >= 0) != (b >= 0):
            have, lack = ("semantic", "instance") if a >= 0 else ("instance", "semantic")
            note_capped(ctx, "frames_with_one_detector_png_missing",
                        f"frame at {stamps[n]} ns: {det_dir / lack}/{stamps[n]}.png is missing (the {have} PNG is "
                        f"there); the frame gets no detections")
        ok = a >= 0 and b >= 0
        sem_paths.append(sem_files[a] if ok else None)
        ins_paths.append(ins_files[b] if ok else None)
    scores = read_scores(det_dir / "scores.csv")
    by_frame: dict[int, pd.DataFrame] = {}
    if len(scores):
        sst = scores["stamp_ns"].to_numpy(np.int64)
        uniq = np.unique(sst)
        frame_of = dict(zip(uniq, match(uniq, stamps, tol)))
        frame_row = np.array([frame_of[s] for s in sst])
        if (frame_row < 0).any():
            ctx.count("scores_rows_without_frame", int((frame_row < 0).sum()))
        scores = scores.assign(frame_row=frame_row)
        by_frame = {k: g for k, g in scores[scores.frame_row >= 0].groupby("frame_row")}
    elif len(ins_st) and not (det_dir / "scores.csv").is_file():
        ctx.note(f"{det_dir / 'scores.csv'} missing: segments taken from the instance PNGs with score 1.0")
    valid = set(c.id for c in DEFAULT_CLASSES) | {VOID}
    rows = []
    for n in range(len(stamps)):
        if ins_paths[n] is None:
            continue
        try:
            inst = read_label(ins_paths[n], "detector instance")
            sem = read_label(sem_paths[n], "detector semantic")
        except ImageError as err:
            if cfg.on_bad_image == "error":
                raise IngestError(str(err)) from None
            note_capped(ctx, "frames_with_unreadable_detector_png", f"frame at {stamps[n]} ns: {err}; the frame "
                                                                    f"gets no detections")
            sem_paths[n] = ins_paths[n] = None
            continue
        if inst.shape != shape or sem.shape != shape:
            raise IngestError(f"detector PNGs {ins_paths[n]} / {sem_paths[n]} are {inst.shape[1]}x{inst.shape[0]} / "
                              f"{sem.shape[1]}x{sem.shape[0]}; the frame is {shape[1]}x{shape[0]}")
        if cmap is not None:
            sem = cmap.lut(np.clip(sem, 0, 255))
        else:
            bad = sorted(set(np.unique(sem).tolist()) - valid)
            if bad:
                raise IngestError(f"detector semantic PNG {sem_paths[n]} holds class ids {bad} that the class table "
                                  f"lacks; classes: {', '.join(f'{c.id}={c.name}' for c in DEFAULT_CLASSES)}, "
                                  f"{VOID} = void (a detector with its own ids: set ingest.class_map)")
        new_rows, stuff = png_pair_segments(n, inst, sem, by_frame.get(n), ctx, cmap)
        rows += new_rows
        if cmap is not None:
            name = f"{stamps[n]}.png"
            write_png(ctx.output_dir("images") / "det" / "semantic" / name, sem.astype(np.uint8))
            write_png(ctx.output_dir("images") / "det" / "instance" / name,
                      np.where(np.isin(inst, sorted(stuff)), 0, inst).astype(np.uint16))
            sem_paths[n] = ins_paths[n] = name  # type: ignore[assignment]
    if cmap is not None:
        voided = cmap.check()
        if voided:
            ctx.count("unmapped_categories_set_to_void", voided)

    def relative(p, kind: str) -> str | None:
        if p is None:
            return None
        return ctx.relpath("images", f"det/{kind}/{p}") if isinstance(p, str) else rel(p, root)

    sem_rel = [relative(p, "semantic") for p in sem_paths]
    ins_rel = [relative(p, "instance") for p in ins_paths]
    if not rows:
        return sem_rel, ins_rel, schemas.empty("detections")
    df = pd.DataFrame(rows, columns=["frame_id", "segment_id", "class_id", "score", "area_px"])
    return sem_rel, ins_rel, df.assign(near_depth_frac=np.nan, kept=True, drop_reason="")


def png_pair_segments(frame_id: int, inst: np.ndarray, sem: np.ndarray, listed: pd.DataFrame | None,
                      ctx: StageContext, cmap: ClassMapper | None = None) -> tuple[list[tuple], set[int]]:
    """Segments of one frame: scores.csv rows (those naming a segment the PNG lacks are skipped and counted)
    and segments of the instance PNG that scores.csv does not list (class by majority of the semantic PNG,
    score 0.5; 1.0 without a scores.csv). Returns the rows and the ids of segments that are not things
    (with a class map: segments mapped to a stuff class or void, which the caller removes)."""
    area = np.bincount(inst.ravel())
    present = set(np.flatnonzero(area[1:]) + 1)
    rows, seen, stuff = [], set(), set()
    if listed is not None:
        for s in listed.itertuples(index=False):
            sid = int(s.segment_id)
            if sid in seen:
                ctx.count("scores_rows_duplicate")
                continue
            if sid not in present:
                ctx.count("scores_rows_for_missing_segments")
                continue
            seen.add(sid)
            klass = cmap(int(s.class_id)) if cmap is not None else int(s.class_id)
            if klass not in THING_IDS:
                if cmap is None:
                    raise IngestError(f"scores.csv row for segment {sid} of frame {frame_id}: class_id {s.class_id} "
                                      f"is not a thing class; thing classes: {list(THING_IDS)}")
                stuff.add(sid)
                continue
            score = float(s.score) if np.isfinite(s.score) else 0.0
            rows.append((frame_id, sid, klass, min(max(score, 0.0), 1.0), int(area[sid])))
    for sid in sorted(present - seen):
        klass = int(np.bincount(sem[inst == sid]).argmax())
        if klass not in THING_IDS:
            stuff.add(int(sid))
            continue
        if listed is not None:
            ctx.count("segments_without_score")
        rows.append((frame_id, int(sid), klass, 1.0 if listed is None else 0.5, int(area[sid])))
    return rows, stuff


def read_coco(raw: Path, det_dir: Path, fmt: str, json_path: Path, obj, stamps: np.ndarray, shape: tuple[int, int],
              cfg: Config, ctx: StageContext) -> tuple[list[str | None], list[str | None], pd.DataFrame]:
    """COCO panoptic or instance results -> label PNGs written under images/det/ and the segments."""
    tol = int(cfg.match_tolerance_ms * 1e6)
    mapping, origin = load_class_map(cfg.class_map, raw)
    reader = CocoPanoptic(json_path, obj, cfg.stamp_unit) if fmt == "coco_panoptic" else \
        CocoInstances(json_path, obj, det_dir / "semantic", cfg.stamp_unit)
    cmap = ClassMapper(mapping, origin, reader.categories, cfg.unmapped, str(json_path))
    for c in reader.categories_used():
        cmap(c)
    cmap.check()
    det_stamps = sorted(reader.by_stamp)
    m = match_stamps(stamps, det_stamps, tol)
    unmatched = len(det_stamps) - len(set(m[m >= 0].tolist()))
    if unmatched:
        ctx.count("detector_images_without_frame", unmatched)
    sem_st, sem_files = index_by_stamp(det_dir / "semantic", cfg.stamp_unit) if fmt == "coco_instances" else \
        (np.zeros(0, np.int64), [])
    m_sem = match(stamps, sem_st, tol)
    out_dir = ctx.output_dir("images")
    sem_rel: list[str | None] = [None] * len(stamps)
    ins_rel: list[str | None] = [None] * len(stamps)
    rows = []
    count = ctx.count
    for n, j in enumerate(ctx.progress(m, "detections", len(m))):
        if j < 0:
            continue
        stamp = det_stamps[j]
        try:
            if fmt == "coco_panoptic":
                labels = reader.labels(stamp, shape, cmap, count)
            else:
                if len(sem_st) and m_sem[n] < 0:
                    note_capped(ctx, "frames_without_semantic_png", f"frame at {stamps[n]} ns: no semantic PNG in "
                                f"{det_dir / 'semantic'}; pixels no mask covers are void")
                labels = reader.labels(stamp, shape, cmap, count, sem_files[m_sem[n]] if m_sem[n] >= 0 else None)
        except UnreadableLabels as err:
            if cfg.on_bad_image == "error":
                raise
            note_capped(ctx, "frames_with_unreadable_detector_png", f"frame at {stamps[n]} ns: {err}; the frame "
                                                                    f"gets no detections")
            continue
        name = f"{stamps[n]}.png"
        write_png(out_dir / "det" / "semantic" / name, labels.semantic)
        write_png(out_dir / "det" / "instance" / name, labels.instance)
        sem_rel[n] = ctx.relpath("images", f"det/semantic/{name}")
        ins_rel[n] = ctx.relpath("images", f"det/instance/{name}")
        rows += [(n, sid, klass, score, area) for sid, klass, score, area in labels.segments]
    voided = cmap.check()
    if voided:
        ctx.count("unmapped_categories_set_to_void", voided)
    if not rows:
        return sem_rel, ins_rel, schemas.empty("detections")
    df = pd.DataFrame(rows, columns=["frame_id", "segment_id", "class_id", "score", "area_px"])
    return sem_rel, ins_rel, df.assign(near_depth_frac=np.nan, kept=True, drop_reason="")
