"""Fuse the windows' instance slots into row-level fruit ids and write per-frame panoptic PNGs with them.
The algorithm is rowmap.fusion (docs/fusion.md); this file reads its inputs and writes the fused frames."""
from __future__ import annotations

from collections import defaultdict
from pathlib import Path

import numpy as np
import pandas as pd

import schemas
from nerf.geometry import pose_matrix, pose_txyzq
from pipeline.classes import THING_IDS, VOID
from pipeline.images import ImageError, write_png
from pipeline.parallel import available_cores, in_order
from pipeline.stage import StageContext
from rowmap.detections import dropped_segments, fruit_segments
from rowmap.fusion import Config, Frame, fit_models, fuse, slot_views
from rowmap.fusion.association import row_fruits, slot_table
from rowmap.geometry import POSE_COLS, window_alignments, with_sensor_depth
from rowmap.renders import PANOPTIC_KINDS, Renders

INPUTS = ("frames", "windows", "window_poses", "window_metrics", "nerf", "renders", "images", "detections_filtered")
OUTPUTS = ("panoptic_frames", "panoptic", "fruit_slots")


def window_views(inputs: dict, renders: Renders, cfg: Config, ctx: StageContext) -> pd.DataFrame:
    """(window_id, frame_id, offset, c2w) of every rendered validation frame of the fitted windows, in the row
    frame. Windows failed or without panoptic renders are skipped with a note; one missing some is an error."""
    wm, wp, windows = inputs["window_metrics"], inputs["window_poses"], inputs["windows"]
    ok = set(wm.loc[wm.status == "ok", "window_id"].astype(int))
    for wid in sorted(set(wm.window_id.astype(int)) - ok):
        ctx.count("windows_failed_skipped")
        ctx.note(f"window {wid} failed in nerf_fit; its frames are not fused")
    val = windows[windows.split == "val"][["window_id", "frame_id", "offset"]]
    v = val.merge(wp, on=["window_id", "frame_id"], how="inner", suffixes=("", "_pose"))
    rows = []
    for wid, g in v[v.window_id.isin(ok)].groupby("window_id"):
        have = [renders.has(int(wid), int(f), *PANOPTIC_KINDS) for f in g.frame_id]
        if not any(have):
            ctx.count("windows_without_panoptic_renders")
            ctx.note(f"window {wid}: no panoptic renders ({'/'.join(PANOPTIC_KINDS)}) in renders.parquet; skipped")
            continue
        if not all(have):
            f = int(g.frame_id.to_numpy()[~np.asarray(have)][0])
            missing = [k for k in PANOPTIC_KINDS if not renders.has(int(wid), f, k)]
            raise ImageError(f"window {wid}, validation frame {f}: renders.parquet lists no {'/'.join(missing)} render "
                             f"while other validation frames of the window have theirs; rerun `pag nerf_fit --force`")
        rows.append(g)
    if not rows:
        return pd.DataFrame(columns=["window_id", "frame_id", "offset", "c2w"])
    out = pd.concat(rows, ignore_index=True)
    out["c2w"] = list(pose_matrix(out[list(POSE_COLS)].to_numpy(np.float64)))
    if cfg.align_windows:
        align = window_alignments(wp[wp.window_id.isin(out.window_id.unique())])
        moved = [align[int(w)] @ c for w, c in zip(out.window_id, out.c2w)]
        # how far a camera moved, not the transform's translation (large for a small rotation about a far origin)
        ctx.summary["window_alignment_max_m"] = round(max(float(np.linalg.norm(m[:3, 3] - c[:3, 3]))
                                                          for m, c in zip(moved, out.c2w)), 4)
        out["c2w"] = moved
    return out[["window_id", "frame_id", "offset", "c2w"]]


def intrinsics(fr) -> np.ndarray:
    return np.array([fr.fx, fr.fy, fr.cx, fr.cy], np.float64)


def read_slots(views: pd.DataFrame, frames: pd.DataFrame, renders: Renders, cfg: Config, ctx: StageContext
               ) -> tuple[dict, dict]:
    """Each render's slot views ((window, slot) -> {(frame, group): SlotView}) and codes ((window, frame) -> [H, W])."""
    def read(r) -> tuple:
        wid, fid = int(r.window_id), int(r.frame_id)
        fr = frames.loc[fid]
        sem, inst, depth = (renders.read(wid, fid, k, (int(fr.height), int(fr.width))) for k in PANOPTIC_KINDS)
        sensor = with_sensor_depth(np.zeros_like(depth), ctx.abspath(fr.depth_path), fr.depth_scale_m)
        return wid, fid, *slot_views(sem, inst, depth, sensor, intrinsics(fr), r.c2w, list(THING_IDS), cfg)

    per_slot: dict[tuple[int, int], dict] = defaultdict(dict)
    codes = {}
    read_all = in_order(read, views.itertuples(index=False), available_cores())
    for wid, fid, found, code_map in ctx.progress(read_all, "read renders", total=len(views)):
        codes[(wid, fid)] = code_map
        for (slot, g), sv in found.items():
            per_slot[(wid, slot)][(fid, g)] = sv
    return per_slot, codes


class FrameReader:
    """One frame's fusion inputs: the nearest window's render with its slots as row fruits, depth, detector."""

    def __init__(self, frames: pd.DataFrame, renders: Renders, nearest: pd.DataFrame, codes: dict, lut: dict,
                 dropped: dict, ctx: StageContext):
        self.frames, self.renders, self.nearest, self.codes = frames, renders, nearest, codes
        self.lut, self.dropped, self.ctx = lut, dropped, ctx

    def render(self, fid: int, kind: str) -> np.ndarray:
        fr = self.frames.loc[fid]
        return self.renders.read(int(self.nearest.window_id[fid]), fid, kind, (int(fr.height), int(fr.width)))

    def frame(self, fid: int) -> Frame:
        fr, wid = self.frames.loc[fid], int(self.nearest.window_id[fid])
        codes = self.codes[(wid, fid)]
        keys, at = np.unique(codes, return_inverse=True)
        fruit = np.array([self.lut[(wid, fid)].get(int(c), 0) for c in keys], np.int64)
        fruit[(fruit == 0) & (keys != 0)] = -1
        label = fruit[at.reshape(codes.shape)]   # row fruit id; 0 stuff, -1 a dropped slot
        depth = with_sensor_depth(self.render(fid, "depth"), self.ctx.abspath(fr.depth_path), fr.depth_scale_m)
        fruit = self.render(fid, "fruit") if self.renders.has(wid, fid, "fruit") else None
        return Frame(fid, label, depth, fruit_segments(fr, self.ctx.data_root, self.dropped.get(fid)), intrinsics(fr),
                     self.nearest.c2w[fid], fruit)


def write_frame(fid: int, fused: np.ndarray, classes: np.ndarray, reader: FrameReader, n_windows: int,
                out_dir: Path, ctx: StageContext) -> dict:
    """Write one fused frame's PNGs (`classes`: fruit id -> class id); its panoptic_frames row."""
    fr, r = reader.frames.loc[fid], reader.nearest.loc[fid]
    label = np.maximum(fused, 0)
    sem_r = reader.render(fid, "semantic")
    stuff = np.where(np.isin(sem_r, THING_IDS), 0, sem_r)     # a thing pixel given no fruit is background
    sem = np.where(fused < 0, VOID, np.where(label > 0, classes[label], stuff))
    name = f"{fid:06d}.png"
    write_png(out_dir / "semantic" / name, sem.astype(np.uint8))
    write_png(out_dir / "instance" / name, label.astype(np.uint16))
    wid = int(r.window_id)
    return {"frame_id": fid, "stamp_ns": int(fr.stamp_ns), "window_id": wid, "offset": int(r.offset),
            "n_windows": n_windows, "semantic_path": ctx.relpath("panoptic", f"semantic/{name}"),
            "instance_path": ctx.relpath("panoptic", f"instance/{name}"),
            "rgb_path": reader.renders.relpath(wid, fid, "rgb"), "n_fruits": int(len(np.unique(label[label > 0]))),
            "depth_path": reader.renders.relpath(wid, fid, "depth"),
            **dict(zip(POSE_COLS, pose_txyzq(r.c2w[None])[0].tolist()))}


def run(inputs: dict, cfg: Config, ctx: StageContext) -> dict[str, pd.DataFrame]:
    frames: pd.DataFrame = inputs["frames"].set_index("frame_id", drop=False)
    renders = Renders(inputs["renders"], ctx.data_root)
    views = window_views(inputs, renders, cfg, ctx)
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
    per_slot, codes = read_slots(views, frames, renders, cfg, ctx)
    local, groups = row_fruits(per_slot, {key: c for key, c in codes.items() if key[1] in shared}, cfg)
    if len(groups) > 65535:
        raise ValueError(f"panoptic_fusion: {len(groups)} fruits do not fit 16-bit instance PNGs (max 65535)")
    nearest = (views.assign(abs_off=views.offset.abs()).sort_values(["frame_id", "abs_off", "window_id"])
               .drop_duplicates("frame_id").set_index("frame_id"))   # each frame's window nearest its centre
    reader = FrameReader(frames, renders, nearest, codes, slot_table(local),
                         dropped_segments(inputs.get("detections_filtered")), ctx)
    models, fused = fuse(nearest.index.astype(int).tolist(), reader.frame, fit_models(groups, local, per_slot, cfg),
                         cfg, ctx.progress)
    classes = np.zeros(max(models, default=0) + 1, np.uint8)
    classes[list(models)] = [m.class_id for m in models.values()]
    rows = [write_frame(fid, label, classes, reader, int(n_win[fid]), out_dir, ctx) for fid, label in fused]
    ctx.count("slots", len(local))
    ctx.count("slots_dropped", sum(lf.fruit_id == 0 for lf in local))
    ctx.summary.update(windows=int(views.window_id.nunique()), frames=len(rows), fruits=max(models, default=0),
                       fruits_split_off=max(models, default=0) - len(groups), frames_in_several_windows=len(shared))
    slots = pd.DataFrame([{
        "window_id": lf.window_id, "slot": lf.slot, "part": lf.part, "fruit_id": lf.fruit_id,
        "class_id": lf.class_id, "n_frames": len({f for f, _ in lf.frames}), "n_px": lf.n_px,
        **{f"{a}_m": None if lf.centre is None else float(lf.centre[i]) for i, a in enumerate("xyz")},
        "drop_reason": lf.drop_reason} for lf in local], columns=schemas.get("fruit_slots").names)
    return {"panoptic_frames": pd.DataFrame(rows, columns=schemas.get("panoptic_frames").names), "fruit_slots": slots}
