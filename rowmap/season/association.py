"""Assign one date's fruits to the open tracks: one gated Hungarian assignment.

Cost of giving fruit j (on the new date, registered into the season frame) to track i (its last
observation, `dt` days earlier):

    c_ij = |p_j - p_i| / gate_m + size_ij,
    size_ij = (max(0, d_i - d_j) + max(0, d_j - d_i - growth_m_per_day dt)) / size_tolerance_m

A pair is admissible when |p_j - p_i| <= gate_m, size_ij <= 1 and the ripeness does not go back by more than
one class (green -> mixed -> red; one step back is left to detector noise). Admissible pairs compete on c;
a fruit left without a track starts one (set or entered the view), a track left without a fruit stays
open for `max_missed_dates` dates. Example: gate 5 cm, tolerance 1 cm: a fruit 2 cm from the track's last
position that grew 3 mm in a week costs 0.4; one that shrank 5 mm costs 0.9.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment

BLOCKED = 1e6
"""Finite cost of an inadmissible pair (the assignment never takes it)."""


@dataclass(frozen=True)
class Gates:
    gate_m: float
    size_tolerance_m: float
    growth_m_per_day: float


def costs(track_xyz: np.ndarray, track_d: np.ndarray, track_class: np.ndarray, dt_days: np.ndarray,
          xyz: np.ndarray, d: np.ndarray, klass: np.ndarray, gates: Gates) -> np.ndarray:
    """[T, F] assignment costs (BLOCKED where inadmissible). Classes are ordinal ripeness ranks (green < mixed
    < red); a NaN diameter is not judged on size."""
    dist = np.linalg.norm(track_xyz[:, None] - xyz[None], axis=2)
    grow = gates.growth_m_per_day * np.asarray(dt_days, np.float64)[:, None]
    dd = np.asarray(d, np.float64)[None] - np.asarray(track_d, np.float64)[:, None]
    size = np.clip(-dd, 0, None) + np.clip(dd - grow, 0, None)
    size = np.nan_to_num(size / gates.size_tolerance_m, nan=0.0)
    c = dist / gates.gate_m + size
    back = np.asarray(track_class)[:, None] - np.asarray(klass)[None]
    blocked = (dist > gates.gate_m) | (size > 1) | (back > 1)
    return np.where(blocked, BLOCKED, c)


def assign(cost: np.ndarray) -> list[tuple[int, int]]:
    """(track, fruit) pairs of the minimum-cost assignment that are admissible."""
    if cost.size == 0:
        return []
    r, c = linear_sum_assignment(cost)
    return [(int(i), int(j)) for i, j in zip(r, c) if cost[i, j] < BLOCKED]
