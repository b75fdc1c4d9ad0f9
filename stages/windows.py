"""Cut the sequence into NeRF windows around the labelled frames, with a train/validation split.

With `cover_row` (default) the windows also cover every frame of the sequence, so the fruit map counts
the whole row: a window next to an uncovered stretch is extended into it (at most `max_extend` frames per
side), a longer stretch gets filler windows (no labelled centre), and neighbouring windows are made to
share at least `min_overlap` frames, which panoptic_fusion aligns the windows on.

Every `val_every`-th frame of the sequence is a validation frame (rendered, fused and scored), counted from
the first window's centre, and every labelled (evaluation) frame is one too; the others train. A frame's
role depends on the frame alone, so a frame shared by overlapping windows has the same role in all of them:
no frame trains one window and validates its neighbour, and a shared validation frame is rendered by every
window that holds it, so panoptic_fusion can take it from the window whose centre is nearest (where the
fruits in it are best covered by training frames).
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
    """frames, >= 1, on each side of the centre frame (clipped at the sequence ends): a window holds up to
    2 * half_width + 1 frames. Wider windows give each fruit more views and cost more time per fit; the
    window should span about as far as the camera moves while a fruit crosses the image."""
    max_windows: int = 0
    """keep at most this many windows, evenly spread (0 = all). For quick runs; a subset leaves stretches of
    the row uncovered, so cover_row is ignored then."""
    unlabelled_spacing: int = 0
    """frames, >= 0: when no frame is labelled, centre windows every this many frames (0 = 2 * half_width,
    windows side by side)."""
    cover_row: bool = True
    """extend windows and add filler windows until every frame is in a window and neighbouring windows share
    min_overlap frames (off = windows only around the labelled frames, as in the paper; frames between them
    are then in no window and their fruits are not counted). Ignored with max_windows."""
    min_overlap: int = 4
    """frames, >= 0 (at most half_width), that neighbouring windows share at least (cover_row). Shared frames
    tie the windows' fruit ids and poses together in panoptic_fusion; where the windows cannot grow that far
    into a gap (max_extend), filler windows are added, so more overlap can cost more fits."""
    grow_overlap: int = 12
    """frames, >= 0 (at most half_width): neighbouring windows grow to share this many frames where they can
    without exceeding max_extend (cover_row; never a filler window for it; below min_overlap = min_overlap).
    A shared validation frame is rendered by both windows: panoptic_fusion ties the two windows' fruits
    together on such frames (centre distance and mask overlap), so a wider overlap links more of the fruits
    entering or leaving a window's stretch of row. Growing costs render time for the added frames, not fit
    steps."""
    context_frames: int = 4
    """frames, >= 0, beyond each end of a window whose role is training also train it (never validate it): a
    fruit entering or leaving the view in a window's first or last validation frames is otherwise seen by one
    or two of its training frames only, where the detector often misses it (cut by the image border). 0 =
    windows train on their own span only."""
    val_every: int = 4
    """frames, >= 2: every val_every-th frame validates (its renders are what panoptic_fusion, fruit_count and
    evaluate read), the others train. At 15 frames a second and 0.2 m/s a near-row fruit stays in view for
    about 60 frames, so 4 still fuses it from about 15 views; 2 renders twice as many and trains on a third fewer."""
    max_extend: int = 0
    """frames, >= 0, a window may grow by on each side to close a gap (cover_row; 0 = half_width); a longer gap
    gets as many filler windows as it needs beyond what its neighbours can grow into. A filler window costs a
    whole fit; growing a window costs no steps but spreads its fixed steps over more frames."""

    def __post_init__(self) -> None:
        if self.half_width < 1:
            raise ValueError(f"windows.half_width must be >= 1, got {self.half_width}")
        if self.max_windows < 0 or self.unlabelled_spacing < 0 or self.max_extend < 0:
            raise ValueError("windows.max_windows, windows.unlabelled_spacing and windows.max_extend must be >= 0")
        if self.val_every < 2:
            raise ValueError(f"windows.val_every must be >= 2 (a window needs training frames), got {self.val_every}")
        if self.context_frames < 0:
            raise ValueError(f"windows.context_frames must be >= 0, got {self.context_frames}")
        if self.min_overlap < 0 or self.grow_overlap < 0:
            raise ValueError(f"windows.min_overlap and windows.grow_overlap must be >= 0, got {self.min_overlap}, "
                             f"{self.grow_overlap}")


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


def spans(centre_pos: list[int], n: int, cfg: Config) -> list[tuple[int, int, int]]:
    """(first, last, centre) frame positions of the windows: one per centre (+-half_width, clipped), and
    with cfg.cover_row the filler windows and extensions that cover positions 0..n-1 with overlaps."""
    hw = cfg.half_width
    out = [(max(0, c - hw), min(n - 1, c + hw), c) for c in sorted(centre_pos)]
    if not cfg.cover_row or cfg.max_windows or not out:
        return out
    ext = cfg.max_extend or hw
    overlap = min(cfg.min_overlap, hw)
    # 1. filler windows in stretches that extending the neighbours cannot close
    filled = []
    for i in range(len(out) + 1):
        lo = out[i - 1][1] + 1 if i else 0                  # first uncovered position of the gap
        hi = out[i][0] - 1 if i < len(out) else n - 1       # last uncovered position
        sides = (i > 0) + (i < len(out))
        need = hi - lo + 1 + (overlap if sides == 2 else 0)
        if hi >= lo and need > ext * sides:
            k = -(-(need - ext * sides) // (2 * hw + 1))     # fillers for what the neighbours cannot grow into
            for c in np.linspace(lo + hw, hi - hw, k) if k > 1 else [(lo + hi) // 2]:
                c = int(round(c))
                filled.append((max(0, c - hw), min(n - 1, c + hw), c))
        if i < len(out):
            filled.append(out[i])
    # 2. extend neighbours to share min_overlap frames (grow_overlap where max_extend allows), and the end
    # windows to the sequence ends
    win = [list(s) for s in sorted(filled, key=lambda s: (s[0], s[2]))]
    nominal = [tuple(w[:2]) for w in win]
    win[0][0], win[-1][1] = 0, n - 1
    target = max(overlap, min(cfg.grow_overlap, hw))
    for (a, b), (na, nb) in zip(zip(win, win[1:]), zip(nominal, nominal[1:])):
        short = overlap - (a[1] - b[0] + 1)
        if short > 0:       # the fillers made this reachable within max_extend
            a[1] = min(n - 1, a[1] + (short + 1) // 2)
            b[0] = max(0, b[0] - short // 2)
        short = target - (a[1] - b[0] + 1)
        if short > 0:       # grow further where max_extend allows
            grow_a = min((short + 1) // 2, max(0, na[1] + ext - a[1]))
            grow_b = min(short - grow_a, max(0, b[0] - (nb[0] - ext)))
            grow_a = min(short - grow_b, max(0, na[1] + ext - a[1]))
            a[1] = min(n - 1, a[1] + grow_a)
            b[0] = max(0, b[0] - grow_b)
    return [tuple(w) for w in win]


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
    labelled = {pos[int(c)] for c in cs} if from_labels else set()
    windows = spans([pos[int(c)] for c in cs], len(ids), cfg)
    n_context = 0
    for w, (lo, hi, i) in enumerate(windows):
        for j in range(max(0, lo - cfg.context_frames), min(len(ids) - 1, hi + cfg.context_frames) + 1):
            off = j - i
            val = (j - anchor) % cfg.val_every == 0 or j in labelled or (off == 0 and not from_labels)
            if not lo <= j <= hi:
                if val:
                    continue            # context frames only train: the window's span is what it renders
                n_context += 1
            rows.append((w, int(ids[j]), int(ids[i]), off, "val" if val else "train", off == 0 and i in labelled))
    df = pd.DataFrame(rows, columns=["window_id", "frame_id", "center_frame_id", "offset", "split", "is_center"])
    df["n_windows"] = df.groupby("frame_id")["window_id"].transform("nunique").astype("int32")
    overlap = int((df.drop_duplicates("frame_id")["n_windows"] > 1).sum())
    fillers = len(windows) - len(cs)
    if fillers:
        ctx.note(f"{fillers} filler window(s) without a labelled centre cover stretches of the row between or "
                 f"beyond the labelled frames (windows.cover_row)")
    ctx.summary.update(windows=len(windows), filler_windows=fillers, context_train_frames=n_context,
                       frames_per_window=round(len(df) / max(len(windows), 1), 1),
                       frames_in_several_windows=overlap, frames_in_no_window=len(ids) - int(df.frame_id.nunique()))
    return {"windows": df}
