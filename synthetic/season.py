"""The row over a season: how each fruit grows, ripens and is harvested, which fruits set, how leaves move.

Time t is in days since the first recording (t = 0 is the row as `build_scene` plans it, unchanged). Every
fruit has a life drawn from its own random stream ([seed, 12, fruit_id]), so the row on any date follows
from the seed alone and two dates of one seed show the same fruits:

    diameter d(t) = d_max - (d_max - d_0) exp(-(t - t_0) / tau)      (t >= t_0, the day it is sized at d_0)
    class         = green before t_mixed, mixed until t_red, red after; harvested at t_harvest (gone)

A fruit on the plant at t = 0 keeps its planned diameter d_0 and class there: a green one still grows
(d_max = d_0 x U(1.05, 1.3), at most MAX_DIAMETER_M; tau = U(10, 20) days / growth_rate_scale) and turns
mixed after U(4, 35) days; a mixed or red one has its final size. Mixed lasts U(3, 8) days; a red fruit
is picked U(4, 10) days after it turned red (a red one at t = 0 is part-way through those). New fruits set during the season (`new_fruits`): small
(U(0.025, 0.035) m) and green, growing to the crop's size U(0.06, 0.09) m with tau = U(8, 14) days, turning
mixed U(35, 50) days after setting.
Example: a green fruit of 70 mm with d_max 84 mm and tau 14 days is 77.0 mm a week later (+1.0 mm/day).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

GREEN, MIXED, RED = 2, 3, 4
MAX_DIAMETER_M = 0.10
"""Largest diameter a fruit grows to (sweet pepper: 6-10 cm)."""
WEEK_DAYS = 7.0
"""New fruits are planned week by week (block k sets fruits in days (7k, 7k + 7])."""


@dataclass(frozen=True)
class FruitLife:
    """One fruit's course through the season (days since the first recording)."""

    d0_m: float
    """diameter at t0_day."""
    d_max_m: float
    """final diameter."""
    tau_day: float
    """growth time constant."""
    t0_day: float
    """day the fruit has diameter d0_m: 0 for a fruit on the plant at the first recording, else its set day."""
    t_mixed_day: float
    t_red_day: float
    t_harvest_day: float

    def diameter_m(self, t: float) -> float:
        if t <= self.t0_day or self.d_max_m == self.d0_m:
            return self.d0_m
        return float(self.d_max_m - (self.d_max_m - self.d0_m) * np.exp(-(t - self.t0_day) / self.tau_day))

    def class_id(self, t: float) -> int:
        return GREEN if t < self.t_mixed_day else MIXED if t < self.t_red_day else RED

    def present(self, t: float) -> bool:
        return self.t0_day <= t < self.t_harvest_day


def life_on_plant(class_id: int, d0_m: float, rng: np.random.Generator, growth_rate_scale: float) -> FruitLife:
    """The life of a fruit found on the plant, of class `class_id` and diameter d0_m, at the first recording."""
    d_max = min(MAX_DIAMETER_M, d0_m * rng.uniform(1.05, 1.3))
    tau = rng.uniform(10.0, 20.0) / growth_rate_scale
    if class_id == GREEN:
        t_mixed = rng.uniform(4.0, 35.0)
        t_red = t_mixed + rng.uniform(3.0, 8.0)
    elif class_id == MIXED:
        d_max = d0_m
        mixed_days = rng.uniform(3.0, 8.0)
        t_red = rng.uniform(0.5, mixed_days)
        t_mixed = t_red - mixed_days
    else:  # red since some of its days on the plant: it is still there at t = 0
        d_max = d0_m
        on_plant_red = rng.uniform(4.0, 10.0)
        t_red = -rng.uniform(0.0, on_plant_red)
        t_mixed = t_red - rng.uniform(3.0, 8.0)
        return FruitLife(d0_m, d0_m, tau, 0.0, t_mixed, t_red, t_red + on_plant_red)
    return FruitLife(d0_m, max(d_max, d0_m), tau, 0.0, t_mixed, t_red, t_red + rng.uniform(4.0, 10.0))


def life_of_new_fruit(set_day: float, rng: np.random.Generator, growth_rate_scale: float) -> FruitLife:
    """The life of a fruit that sets on `set_day`, small and green."""
    d0, d_max = rng.uniform(0.025, 0.035), rng.uniform(0.06, 0.09)
    tau = rng.uniform(8.0, 14.0) / growth_rate_scale
    t_mixed = set_day + rng.uniform(35.0, 50.0)
    t_red = t_mixed + rng.uniform(3.0, 8.0)
    return FruitLife(d0, d_max, tau, set_day, t_mixed, t_red, t_red + rng.uniform(4.0, 10.0))


def leaf_motion(rng: np.random.Generator, day: float) -> tuple[np.ndarray, float, float]:
    """(axis [3], angle_rad, scale) of a leaf `day` days after the first recording: it turns by 2-6 degrees
    about a random axis and grows by up to 10 %, both growing linearly over three weeks; no change on day 0."""
    axis = rng.normal(size=3)
    angle = np.radians(rng.uniform(2.0, 6.0)) * min(day / 21.0, 1.0)
    grow = 1.0 + rng.uniform(0.0, 0.10) * min(day / 21.0, 1.0)
    return axis, float(angle) if day > 0 else 0.0, float(grow) if day > 0 else 1.0
