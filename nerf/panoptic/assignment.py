"""Per-frame optimal assignment of detected thing segments to instance slots, with repeated-ID rejection.

The instance head predicts a distribution p over N slots per ray (slot 0 = stuff). For one frame
with S detected thing segments, the cost of giving segment n slot m is

    C[n, m] = - mean_{rays r in segment n} p_m(r)          (in [-1, 0])

and scipy's linear_sum_assignment picks the slot per segment minimising the total cost; slot 0 is
never given to a thing. Repeated-ID rejection: fruits at opposite ends of the row are never seen
together, so plain assignment may give them the same slot. Each segment may only take the slots in
a circular window that slides with the segment's position s (metres along the trajectory):

    centre(s) = s * slope (in slots),  allowed(m) = ((m - 1) - centre + width / 2) mod n_thing < width

with slope = width / frustum_length, so two segments one frustum length apart have disjoint windows
(needs n_thing_slots >= 2 * width). Disallowed slots cost `OUTSIDE_COST`, large but finite, so the
assignment never sees inf/NaN and still returns a slot when every slot is outside (it will not
happen with a sensible width, and the cost then says so).
Example: width 8, frustum 0.5 m -> slope 16 slots/m; s = 0 allows slots 1-4 and 61-64 (of 64
thing slots), s = 0.5 m allows slots 5-12.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy.optimize import linear_sum_assignment

OUTSIDE_COST = 10.0
"""Cost of a slot outside a segment's window: larger than any probability-based cost (which lie in [-1, 0])."""


@dataclass(frozen=True)
class SlotWindow:
    """The sliding slot window of repeated-ID rejection."""

    width: int
    """slots a segment may choose from (max fruits across one frustum length + margin)."""
    slope_per_m: float
    """window shift in slots per metre along the trajectory (= width / frustum length)."""
    n_thing_slots: int
    """slots 1..n_thing_slots; slot 0 is stuff."""

    @staticmethod
    def for_scene(max_fruits_per_frustum: int, frustum_length_m: float, n_slots: int, margin: int = 4) -> "SlotWindow":
        """Width from the busiest frame (+ margin), slope so one frustum length shifts by a full width."""
        if frustum_length_m <= 0:
            raise ValueError(f"frustum_length_m must be > 0, got {frustum_length_m}")
        n_thing = n_slots - 1
        width = int(max_fruits_per_frustum) + int(margin)
        if n_thing < 2 * width:
            raise ValueError(f"{n_slots} instance slots are too few for repeated-ID rejection: a window of "
                             f"{width} slots (max {max_fruits_per_frustum} fruits per frame + margin {margin}) "
                             f"needs at least {2 * width + 1} slots")
        return SlotWindow(width, width / frustum_length_m, n_thing)

    def allowed(self, along_m: np.ndarray) -> np.ndarray:
        """[S] positions along the trajectory -> [S, n_thing_slots + 1] bool (column 0 = stuff, never allowed)."""
        centre = np.asarray(along_m, np.float64)[:, None] * self.slope_per_m   # [S, 1] in slots
        m = np.arange(self.n_thing_slots)[None, :]                               # slot m+1 sits at m
        inside = (m - centre + self.width / 2) % self.n_thing_slots < self.width  # exactly `width` slots
        return np.concatenate([np.zeros((len(centre), 1), bool), inside], axis=1)


def position_preference(window: SlotWindow, along_m: np.ndarray) -> np.ndarray:
    """[S] positions along the trajectory -> [S, n_thing_slots + 1] in [0, 1]: the circular distance, in
    window widths, between each slot and the slot the segment's position maps to (column 0 = stuff, 1).
    Added with a small weight to the assignment cost it breaks the ties of an untrained instance head
    the same way in every frame (a fruit's position along the row does not change between frames), so
    the first assignments are already consistent; learned probabilities outweigh it later."""
    centre = np.asarray(along_m, np.float64)[:, None] * window.slope_per_m
    m = np.arange(window.n_thing_slots)[None, :]
    diff = (m - centre) % window.n_thing_slots
    dist = np.minimum(diff, window.n_thing_slots - diff) / max(window.width, 1)
    return np.concatenate([np.ones((len(centre), 1)), np.clip(dist, 0.0, 1.0)], axis=1)


def segment_costs(probs: torch.Tensor, seg_index: torch.Tensor, n_segments: int) -> torch.Tensor:
    """Mean slot probability per segment, negated. probs [R, N] (rows sum to 1), seg_index [R] in
    0..n_segments-1 (rays of stuff excluded by the caller) -> cost [n_segments, N]."""
    n = probs.shape[1]
    sums = torch.zeros(n_segments, n, dtype=probs.dtype, device=probs.device).index_add_(0, seg_index, probs)
    counts = torch.bincount(seg_index, minlength=n_segments).clamp_min(1).to(probs.dtype)
    return -(sums / counts[:, None])


def assign(cost: np.ndarray, allowed: np.ndarray | None = None) -> np.ndarray:
    """Optimal slot per segment. cost [S, N] (column 0 = stuff), allowed [S, N] bool or None.
    Returns [S] slots in 1..N-1; all distinct while S <= N - 1, else the extra segments reuse
    slots (each in its own optimal second round) and are reported by the caller."""
    cost = np.nan_to_num(np.asarray(cost, np.float64), nan=OUTSIDE_COST, posinf=OUTSIDE_COST, neginf=-1.0)
    s, n = cost.shape
    if n < 2:
        raise ValueError(f"need at least 2 instance slots (slot 0 is stuff), got {n}")
    c = cost[:, 1:].copy()
    if allowed is not None:
        c[~allowed[:, 1:]] = OUTSIDE_COST
    out = np.empty(s, np.int64)
    todo = np.arange(s)
    while len(todo):
        rows, cols = linear_sum_assignment(c[todo])
        out[todo[rows]] = cols + 1
        todo = np.setdiff1d(todo, todo[rows])
    return out


def along_track(points: np.ndarray, cam_positions: np.ndarray) -> np.ndarray:
    """Position of points [S, 3] along the main direction of the camera trajectory [K, 3], in metres,
    measured from the trajectory's first camera. A straight row makes this the distance along the row."""
    cams = np.asarray(cam_positions, np.float64)
    if len(cams) < 2:
        return np.zeros(len(points))
    centred = cams - cams.mean(0)
    axis = np.linalg.svd(centred, full_matrices=False)[2][0]
    if axis @ (cams[-1] - cams[0]) < 0:
        axis = -axis
    return (np.asarray(points, np.float64) - cams[0]) @ axis


class SlotMemory:
    """Where each instance slot's fruit is: the 3D centre of the segments assigned to the slot so far.

    A fruit does not move between frames, so the segment of the same fruit in another frame should take
    the same slot. `cost` turns that into an assignment term in [0, 1]: the distance from a segment's
    centre to each slot's remembered centre in units of the segment's size (0 = same place, 1 = one
    segment size or more away, i.e. another fruit), and `UNSEEN` for slots no segment took yet, so a fruit
    seen for the first time prefers a free slot to another fruit's. Centres are running means that turn
    into an exponential average (rate `min_rate`), so early, poorly placed segments are forgotten.
    """

    UNSEEN = 0.5

    def __init__(self, n_slots: int, min_rate: float = 0.05):
        self.centre = np.zeros((n_slots, 3))
        self.count = np.zeros(n_slots, np.int64)
        self.min_rate = min_rate

    def cost(self, centres: np.ndarray, sizes: np.ndarray) -> np.ndarray:
        """centres [S, 3] (m), sizes [S] (m, > 0) -> [S, n_slots] in [0, 1]; column 0 (stuff) is 1."""
        d = np.linalg.norm(np.asarray(centres, np.float64)[:, None] - self.centre[None], axis=2)
        c = np.clip(d / np.maximum(np.asarray(sizes, np.float64), 1e-6)[:, None], 0.0, 1.0)
        c[:, self.count == 0] = self.UNSEEN
        c[:, 0] = 1.0
        return c

    def update(self, slots: np.ndarray, centres: np.ndarray) -> None:
        """Move the centres of `slots` [S] towards the segments' `centres` [S, 3] they were given."""
        for m, x in zip(np.asarray(slots, np.int64), np.asarray(centres, np.float64)):
            if not np.isfinite(x).all():
                continue
            self.count[m] += 1
            rate = max(1.0 / self.count[m], self.min_rate)
            self.centre[m] += rate * (x - self.centre[m])


def segment_geometry(points: np.ndarray, seg: np.ndarray, n_segments: int) -> tuple[np.ndarray, np.ndarray]:
    """Robust 3D centre (per-axis median) and size (2 x median distance to the centre, >= 1 mm) of each
    segment's points [R, 3]; seg [R] in 0..n_segments-1."""
    centres = np.zeros((n_segments, 3))
    sizes = np.full(n_segments, 1e-3)
    for s in range(n_segments):
        p = points[seg == s]
        p = p[np.isfinite(p).all(1)]
        if len(p) == 0:
            centres[s] = np.nan
            continue
        centres[s] = np.median(p, axis=0)
        sizes[s] = max(2.0 * float(np.median(np.linalg.norm(p - centres[s], axis=1))), 1e-3)
    return centres, sizes
