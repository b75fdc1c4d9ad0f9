"""Fuse the windows' instance slots into row-level fruit ids and write per-frame panoptic PNGs with them.

The algorithm is rowmap.fusion (docs/fusion.md); this file reads the renders, detector output and sensor
depth, and writes the fused frames and tables."""
from __future__ import annotations

from collections import defaultdict

import numpy as np
import pandas as pd

import schemas
from nerf.geometry import pose_matrix, pose_txyzq
from pipeline.classes import THING_IDS, VOID
from pipeline.images import ImageError, write_png
from pipeline.stage import StageContext
from rowmap.detections import dropped_segments, fruit_segments
from rowmap.fusion import Config, Frame, associate, fit_models, fuse, local_fruits, render_label, slot_views
from rowmap.fusion.association import code
from rowmap.geometry import POSE_COLS, window_alignments, with_sensor_depth
from rowmap.renders import PANOPTIC_KINDS, Renders, encode

INPUTS = ("frames", "windows", "window_poses", "window_metrics", "nerf", "renders", "images", "detections_filtered")
OUTPUTS = ("panoptic_frames", "panoptic", "fruit_slots")
__all__ = ["Config", "INPUTS", "OUTPUTS", "run"]


def window_views(windows: pd.DataFrame, window_poses: pd.DataFrame, window_metrics: pd.DataFrame,
                 renders: Renders, ctx: StageContext) -> pd.DataFrame:
    """(window_id, frame_id, offset, c2w) of every rendered validation frame of the fitted windows. Failed
    windows and windows without panoptic renders are skipped with a note; a window with panoptic renders for
    some validation frames but not others is an error naming what is missing."""
    ok = set(window_metrics.loc[window_metrics.status == "ok", "window_id"].astype(int))
    for wid in sorted(set(window_metrics.window_id.astype(int)) - ok):
        ctx.count("windows_failed_skipped")
        ctx.note(f"window {wid} failed in nerf_fit; its frames are not fused")
    val = windows[windows.split == "val"][["window_id", "frame_id", "offset"]]
    v = val.merge(window_poses, on=["window_id", "frame_id"], how="inner", suffixes=("", "_pose"))
    rows = []
    for wid, g in v.groupby("window_id"):
        have = [renders.has(int(wid), int(f), *PANOPTIC_KINDS) for f in g.frame_id]
        if int(wid) not in ok:
            continue
        if not any(have):
            ctx.count("windows_without_panoptic_renders")
            ctx.note(f"window {wid}: no panoptic renders ({'/'.join(PANOPTIC_KINDS)}) in renders.parquet; skipped")
            continue
        if not all(have):
            f = int(g.frame_id.to_numpy()[~np.asarray(have)][0])
            missing = [k for k in PANOPTIC_KINDS if not renders.has(int(wid), f, k)]
            raise ImageError(f"window {wid}, validation frame {f}: renders.parquet lists no {'/'.join(missing)} "
                             f"render while other validation frames of the window have theirs; rerun "
                             f"`pag nerf_fit --force`")
        rows.append(g)
    if not rows:
        return pd.DataFrame(columns=["window_id", "frame_id", "offset", "c2w"])
    out = pd.concat(rows, ignore_index=True)
    out["c2w"] = list(pose_matrix(out[list(POSE_COLS)].to_numpy(np.float64)))
    return out[["window_id", "frame_id", "offset", "c2w"]]


def intrinsics(fr) -> np.ndarray:
    return np.array([fr.fx, fr.fy, fr.cx, fr.cy], np.float64)


def read_slots(views: pd.DataFrame, frames: pd.DataFrame, renders: Renders, shared: set[int], cfg: Config,
               ctx: StageContext) -> tuple[dict, dict, dict]:
    """Every rendered frame's slot views ((window, slot) -> {(frame, group): SlotView}), the slot-code masks of
    the frames several windows rendered ((window, frame) -> [H, W]) and each render's group map."""
    per_slot: dict[tuple[int, int], dict] = defaultdict(dict)
    masks, groups = {}, {}
    for r in ctx.progress(views.itertuples(index=False), "read renders", total=len(views)):
        wid, fid = int(r.window_id), int(r.frame_id)
        fr = frames.loc[fid]
        sem, inst, depth = (renders.read(wid, fid, k, (int(fr.height), int(fr.width))) for k in PANOPTIC_KINDS)
        sensor = with_sensor_depth(np.zeros_like(depth), ctx.abspath(fr.depth_path), fr.depth_scale_m)
        found, group = slot_views(sem, inst, depth, sensor, intrinsics(fr), r.c2w, list(THING_IDS), cfg)
        for (slot, g), sv in found.items():
            per_slot[(wid, slot)][(fid, g)] = sv
        groups[(wid, fid)] = group
        if fid in shared:
            masks[(wid, fid)] = np.where(np.isin(sem, THING_IDS) & (inst > 0), code(inst, group), 0).astype(np.int32)
    return per_slot, masks, groups


def run(inputs: dict, cfg: Config, ctx: StageContext) -> dict[str, pd.DataFrame]:
    frames: pd.DataFrame = inputs["frames"].set_index("frame_id", drop=False)
    renders = Renders(inputs["renders"], ctx.data_root)
    views = window_views(inputs["windows"], inputs["window_poses"], inputs["window_metrics"], renders, ctx)
    if cfg.align_windows and not views.empty:
        wp = inputs["window_poses"]
        align = window_alignments(wp[wp.window_id.isin(views.window_id.unique())])
        views["c2w"] = [align[int(w)] @ c for w, c in zip(views.window_id, views.c2w)]
        ctx.summary["window_alignment_max_m"] = round(max(float(np.linalg.norm(t[:3, 3])) for t in align.values()), 4)
    out_dir = ctx.output_dir("panoptic")
    for sub in ("semantic", "instance"):
        (out_dir / sub).mkdir(parents=True, exist_ok=True)
    if views.empty:
        ctx.note("no window has panoptic renders: nothing fused, tables are empty")
        ctx.summary.update(frames=0, fruits=0)
        return {"panoptic_frames": schemas.empty("panoptic_frames"), "fruit_slots": schemas.empty("fruit_slots")}
    missing = sorted(set(views.frame_id.astype(int)) - set(frames.index.astype(int)))
    if missing:
        raise ValueError(f"panoptic_fusion: window_poses/windows list frames {missing[:10]} that are not in "
                         f"frames.parquet; rerun the pipeline from ingest")
    n_win = views.groupby("frame_id").window_id.nunique()
    shared = set(n_win[n_win > 1].index.astype(int))
    per_slot, masks, group_maps = read_slots(views, frames, renders, shared, cfg, ctx)
    local = local_fruits(per_slot, cfg)
    groups = associate(local, masks, cfg)
    # row-level ids increase along the row (x, then z); fruits a split adds follow
    centre = [np.median(np.stack([local[i].centre for i in g]), 0) for g in groups]
    for fruit_id, j in enumerate(sorted(range(len(groups)), key=lambda j: (centre[j][0], centre[j][2], centre[j][1])), 1):
        for i in groups[j]:
            local[i].fruit_id = fruit_id
    models = fit_models(groups, local, per_slot, cfg)
    lut: dict[tuple[int, int], dict[int, int]] = defaultdict(dict)   # (window, frame) -> {slot code: fruit}
    support: dict[int, dict[int, float]] = defaultdict(lambda: defaultdict(float))   # window -> fruit -> frames
    for lf in local:
        for f, g in lf.frames:
            lut[(lf.window_id, f)][int(code(lf.slot, g))] = lf.fruit_id
        if lf.fruit_id:
            support[lf.window_id][lf.fruit_id] += len({f for f, _ in lf.frames}) + lf.n_px * 1e-9
    pick = views.assign(abs_off=views.offset.abs()).sort_values(["frame_id", "abs_off", "window_id"])
    by_frame = {int(f): g for f, g in pick.groupby("frame_id", sort=True)}
    dropped = dropped_segments(inputs.get("detections_filtered"))
    extra: dict[int, tuple] = {}   # frame -> (semantic, depth, composed) of the frame last loaded

    def load(fid: int) -> Frame:
        fr, rows = frames.loc[fid], by_frame[fid]
        shape = (int(fr.height), int(fr.width))
        sems, labels, depths = [], [], []
        for w in rows.window_id.astype(int):
            sem, inst, depth = (renders.read(w, fid, k, shape) for k in PANOPTIC_KINDS)
            codes = code(inst.astype(np.int64), group_maps[(w, fid)])
            thing = np.isin(sem, THING_IDS) & (inst > 0)
            table = lut[(w, fid)]
            keys = np.unique(codes[thing])
            mapped = np.array([table.get(int(c), 0) for c in keys], np.int64)
            label = np.zeros(shape, np.int64)
            label[thing] = np.where(mapped == 0, -1, mapped)[np.searchsorted(keys, codes[thing])]
            sems.append(sem), labels.append(label), depths.append(depth)
        label, src = render_label(labels, [support[int(w)] for w in rows.window_id])
        pick_ = lambda images: np.take_along_axis(np.stack(images), src[None], 0)[0]   # noqa: E731
        depth = pick_(depths)
        extra[fid] = (pick_(sems), depth, bool((src > 0).any()))
        return Frame(fid, label, with_sensor_depth(depth, ctx.abspath(fr.depth_path), fr.depth_scale_m),
                     fruit_segments(fr, ctx.data_root, dropped.get(fid)), intrinsics(fr), rows.c2w.iloc[0])

    out_rows, n_fruits = [], len(groups)
    for fid, fused, models in fuse(sorted(by_frame), load, models, cfg, ctx.progress):
        fr, r = frames.loc[fid], by_frame[fid].iloc[0]
        sem_r, depth, composed = extra.pop(fid)
        classes = np.zeros(max(models, default=0) + 1, np.uint8)
        for f, m in models.items():
            classes[f] = m.class_id
        label = np.maximum(fused, 0)
        sem = np.where(fused < 0, VOID, np.where(label > 0, classes[label], np.where(np.isin(sem_r, THING_IDS), 0, sem_r)))
        name = f"{fid:06d}.png"
        write_png(out_dir / "semantic" / name, sem.astype(np.uint8))
        write_png(out_dir / "instance" / name, label.astype(np.uint16))
        depth_path = renders.relpath(int(r.window_id), fid, "depth")
        if composed:
            ctx.count("frames_composed_from_several_windows")
            (out_dir / "depth").mkdir(exist_ok=True)
            write_png(out_dir / "depth" / name, encode("depth", depth))
            depth_path = ctx.relpath("panoptic", f"depth/{name}")
        n_fruits = max(n_fruits, max(models, default=0))
        out_rows.append({"frame_id": fid, "stamp_ns": int(fr.stamp_ns), "window_id": int(r.window_id),
                         "offset": int(r.offset), "n_windows": int(n_win[fid]),
                         "semantic_path": ctx.relpath("panoptic", f"semantic/{name}"),
                         "instance_path": ctx.relpath("panoptic", f"instance/{name}"),
                         "rgb_path": renders.relpath(int(r.window_id), fid, "rgb"), "depth_path": depth_path,
                         "n_fruits": int(len(np.unique(label[label > 0]))),
                         **dict(zip(POSE_COLS, pose_txyzq(r.c2w[None])[0].tolist()))})
    if n_fruits > 65535:
        raise ValueError(f"panoptic_fusion: {n_fruits} fruits do not fit 16-bit instance PNGs (max 65535)")
    slots = pd.DataFrame([{
        "window_id": lf.window_id, "slot": lf.slot, "part": lf.part, "fruit_id": lf.fruit_id,
        "class_id": lf.class_id, "n_frames": len({f for f, _ in lf.frames}), "n_px": lf.n_px,
        **{f"{a}_m": None if lf.centre is None else float(lf.centre[i]) for i, a in enumerate("xyz")},
        "drop_reason": lf.drop_reason} for lf in local], columns=schemas.get("fruit_slots").names)
    ctx.count("slots", len(local))
    ctx.count("slots_dropped", sum(lf.fruit_id == 0 for lf in local))
    ctx.summary.update(windows=int(views.window_id.nunique()), frames=len(out_rows), fruits=n_fruits,
                       frames_in_several_windows=len(shared))
    return {"panoptic_frames": pd.DataFrame(out_rows, columns=schemas.get("panoptic_frames").names),
            "fruit_slots": slots}
