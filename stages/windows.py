"""Cut the sequence into NeRF windows around the labelled frames, with a train/validation split.

Every other frame of the sequence is a validation frame, counted from the first window's centre, and
every window's centre frame (the labelled, evaluation frame) is one too. A frame shared by overlapping
windows thus has the same role in all of them: no frame trains one window and validates its neighbour,
and a shared validation frame is rendered by every window that holds it, so panoptic_fusion can take
it from the window whose centre is nearest (where the fruits in it are best covered by training frames).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from pipeline.stage import StageContext

INPUTS = ("frames",)
OUTPUTS = ("windows",)


@dataclass(frozen=True)
class Config:
    half_width: int = 20
    """frames on each side of the centre frame (clipped at the sequence ends)."""
    max_windows: int = 0
    """keep at most this many windows, evenly spread (0 = all)."""
    unlabelled_spacing: int = 0
    """when no frame is labelled, centre windows every this many frames (0 = 2 * half_width)."""

    def __post_init__(self) -> None:
        if self.half_width < 1:
            raise ValueError(f"windows.half_width must be >= 1, got {self.half_width}")
        if self.max_windows < 0 or self.unlabelled_spacing < 0:
            raise ValueError("windows.max_windows and windows.unlabelled_spacing must be >= 0")


def centres(frame_ids: np.ndarray, labelled: np.ndarray, cfg: Config) -> tuple[np.ndarray, bool]:
    """Centre frames: the labelled ones, else evenly spaced. Returns (centres, from_labels)."""
    if labelled.any():
        c = frame_ids[labelled]
        from_labels = True
    else:
        step = cfg.unlabelled_spacing or 2 * cfg.half_width
        c = frame_ids[min(cfg.half_width, len(frame_ids) - 1)::step]
        from_labels = False
    if cfg.max_windows and len(c) > cfg.max_windows:
        c = c[np.round(np.linspace(0, len(c) - 1, cfg.max_windows)).astype(int)]
    return c, from_labels


def run(inputs: dict, cfg: Config, ctx: StageContext) -> dict[str, pd.DataFrame]:
    frames: pd.DataFrame = inputs["frames"].sort_values("frame_id")
    if frames.empty:
        raise ValueError("windows: the frames table is empty; nothing to cut into windows")
    ids = frames["frame_id"].to_numpy()
    pos = {int(f): i for i, f in enumerate(ids)}
    cs, from_labels = centres(ids, frames["labelled"].to_numpy(bool), cfg)
    if not from_labels:
        ctx.note(f"no labelled frames: {len(cs)} windows centred every "
                 f"{cfg.unlabelled_spacing or 2 * cfg.half_width} frames (no evaluation frame)")
    rows = []
    anchor = pos[int(cs[0])] if len(cs) else 0
    for w, c in enumerate(cs):
        i = pos[int(c)]
        for j in range(max(0, i - cfg.half_width), min(len(ids), i + cfg.half_width + 1)):
            off = j - i
            val = off == 0 or (j - anchor) % 2 == 0
            rows.append((w, int(ids[j]), int(c), off, "val" if val else "train", off == 0 and from_labels))
    df = pd.DataFrame(rows, columns=["window_id", "frame_id", "center_frame_id", "offset", "split", "is_center"])
    df["n_windows"] = df.groupby("frame_id")["window_id"].transform("nunique").astype("int32")
    overlap = int((df.drop_duplicates("frame_id")["n_windows"] > 1).sum())
    ctx.summary.update(windows=len(cs), frames_per_window=round(len(df) / max(len(cs), 1), 1),
                       frames_in_several_windows=overlap)
    return {"windows": df}
