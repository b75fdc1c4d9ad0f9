"""Drop detected (and ground-truth) fruit masks that are mostly beyond the near row's depth."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

import schemas
from pipeline.classes import THING_IDS
from pipeline.images import read_depth_m, read_label
from pipeline.parallel import available_cores, in_order
from pipeline.stage import StageContext

INPUTS = ("frames", "detections")
OUTPUTS = ("detections_filtered", "gt_segments")


@dataclass(frozen=True)
class Config:
    max_depth_m: float = 1.5
    """metres, > 0: depth beyond which a pixel is not part of the near row (the far row is behind it). Set it
    between the near row's far side and the next row, from the row spacing and the camera's distance to the
    row; fruit_count.max_depth_m should match."""
    min_near_frac: float = 0.5
    """share in [0, 1]: a mask is kept when at least this share of its pixels has valid depth within
    max_depth_m. Lower it when depth is often missing on fruits (shiny skin, sensor holes), raise it when
    far-row fruits seen past near-row leaves are kept."""

    def __post_init__(self) -> None:
        if not self.max_depth_m > 0:
            raise ValueError(f"depth_filter.max_depth_m must be > 0, got {self.max_depth_m}")
        if not 0.0 <= self.min_near_frac <= 1.0:
            raise ValueError(f"depth_filter.min_near_frac must be in [0, 1], got {self.min_near_frac}")


def near_fractions(instance: np.ndarray, near: np.ndarray, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per id: (area in px, share of its pixels where `near` is true). Shapes: [H, W] x2, [K] -> [K], [K]."""
    flat = instance.ravel()
    size = max(int(flat.max(initial=0)), int(ids.max(initial=0))) + 1
    area = np.bincount(flat, minlength=size)
    hits = np.bincount(flat, weights=near.ravel().astype(np.float64), minlength=size)
    a = area[ids]
    frac = np.divide(hits[ids], a, out=np.zeros(len(ids)), where=a > 0)
    return a, frac


def verdict(area: np.ndarray, frac: np.ndarray, cfg: Config) -> tuple[np.ndarray, list[str]]:
    kept = (area > 0) & (frac >= cfg.min_near_frac)
    reasons = ["" if k else ("empty mask: no pixels in the instance PNG" if a == 0 else
               f"depth: {100 * f:.0f}% of pixels within {cfg.max_depth_m:g} m (< {100 * cfg.min_near_frac:.0f}%)")
               for k, a, f in zip(kept, area, frac)]
    return kept, reasons


def run(inputs: dict, cfg: Config, ctx: StageContext) -> dict[str, pd.DataFrame]:
    frames: pd.DataFrame = inputs["frames"]
    dets: pd.DataFrame = inputs["detections"].copy()
    segment_ids = dets["segment_id"].to_numpy()
    rows_of = dets.groupby("frame_id").indices   # frame -> row positions in dets
    near_frac, kept_all = np.full(len(dets), np.nan), np.ones(len(dets), bool)
    drop_reason = np.full(len(dets), "", object)

    def check(fr) -> tuple:
        """One frame's (detector masks' (area, near share, kept, reasons) or None, ground-truth rows), on a
        worker thread."""
        depth = read_depth_m(ctx.abspath(fr.depth_path), fr.depth_scale_m)
        near = (depth > 0) & (depth <= cfg.max_depth_m)
        pos, det, rows = rows_of.get(fr.frame_id), None, []
        if pos is not None and isinstance(fr.det_instance_path, str):
            inst = read_label(ctx.abspath(fr.det_instance_path), "detector instance")
            if inst.shape != depth.shape:
                raise ValueError(f"frame {fr.frame_id}: detector instance PNG {fr.det_instance_path} is "
                                 f"{inst.shape}, depth is {depth.shape}")
            area, frac = near_fractions(inst, near, segment_ids[pos])
            det = (pos, frac, *verdict(area, frac, cfg))
        if isinstance(fr.gt_instance_path, str) and isinstance(fr.gt_semantic_path, str):
            inst = read_label(ctx.abspath(fr.gt_instance_path), "ground-truth instance")
            sem = read_label(ctx.abspath(fr.gt_semantic_path), "ground-truth semantic")
            ids = np.unique(inst[(inst > 0) & np.isin(sem, THING_IDS)])
            if len(ids):
                area, frac = near_fractions(inst, near, ids)
                kept, reasons = verdict(area, frac, cfg)
                for i, a, f, k, r in zip(ids, area, frac, kept, reasons):
                    cls = np.bincount(sem[inst == i]).argmax()
                    rows.append((fr.frame_id, int(i), int(cls), int(a), float(f), bool(k), r))
        return det, rows

    gt_rows = []
    checked = in_order(check, frames.itertuples(index=False), available_cores())
    for det, rows in ctx.progress(checked, "frames", total=len(frames)):
        if det is not None:
            pos, frac, kept, reasons = det
            near_frac[pos], kept_all[pos], drop_reason[pos] = frac, kept, reasons
        gt_rows += rows
    dets["near_depth_frac"], dets["kept"], dets["drop_reason"] = near_frac, kept_all, drop_reason
    gt = pd.DataFrame(gt_rows, columns=schemas.get("gt_segments").names) if gt_rows else schemas.empty("gt_segments")
    n_drop = int((~dets["kept"]).sum())
    ctx.summary.update(segments=len(dets), dropped=n_drop, gt_segments=len(gt),
                       gt_dropped=int((~gt["kept"]).sum()) if len(gt) else 0)
    return {"detections_filtered": dets, "gt_segments": gt}
