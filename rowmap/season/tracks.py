"""A season of one row: dates in time order -> fruit tracks, per-track summary and per-date registration.

Date by date: register the date's counted fruits onto the open tracks' last positions (registration.py; the
first date defines the season frame), assign them to the tracks (association.py), give the tracks not yet red
that are left over the fruits left over at their place however much they grew (only ripe fruits are picked),
start a track for every fruit still left. Events are read off the finished tracks, so a fruit missed on one
date and seen again is neither harvested nor set:

- `set`: the first observation of a track, not on the first date, of a fruit no wider than
  set_max_diameter_m, lying inside the stretch of row the previous date recorded (so it would have been
  seen had it been there), unless the track is lost after that one observation;
- `harvested`: a row on the date after a track's last observation when the fruit lies inside that date's
  stretch (diameter, class and fruit_id null: the fruit is gone), unless the track is lost: it ended before
  its fruit was ever seen as ripe as PICKED_FROM (mixed) and the next date came sooner than ripen_days after its
  last sighting; growers pick ripe fruits, so such a green track was a false fruit or a fruit the later dates
  miss;
- `present`: every other observation (the first date's fruits, fruits that entered the view, fruits seen again).

The recorded stretch of a date is the x range of its cameras in the season frame, less edge_margin_m at
either end.
"""
from __future__ import annotations

import datetime as dt
from dataclasses import dataclass

import numpy as np
import pandas as pd

from rowmap import structure
from rowmap.season import association, registration

RIPENESS_RANK = {"fruit_green": 0, "fruit_mixed": 1, "fruit_red": 2}
"""Ordinal ripeness of the fruit classes (pipeline/classes.py names); other names rank with green."""
RED = "fruit_red"
PICKED_FROM = "fruit_mixed"
"""the least ripe class a fruit is picked at: a track that ends before it reached this class, sooner than
ripen_days after it was last seen, is lost (a false fruit, or one the later dates miss), not harvested."""
LEFTOVER_SHRINK = 2.0
"""multiple of size_tolerance_m a not-yet-red track left over after the assignment may shrink by to take a fruit
left over at its place (twice the tolerance: two diameters' noise, against one fruit gone and another there)."""


SUMMARY_COLUMNS = ["track_id", "n_dates", "first_seq", "first_date", "last_date", "first_day", "last_day", "set_date",
                   "date_red", "days_to_red", "date_harvested", "day_harvested", "growth_mm_per_day",
                   "diameter_first_m", "diameter_last_m", "class_first", "class_last", "x_m", "y_m", "z_m"]
"""Columns of the per-track summary (schemas/fruit_track_summary.py documents them)."""


@dataclass(frozen=True)
class Config:
    gate_m: float = 0.05
    """largest distance (m, > 0) between a track's last position and a fruit of a later date, after
    registration, for them to be one fruit. Raise it when the rows' maps drift by more than a few cm."""
    size_tolerance_m: float = 0.01
    """diameter measurement tolerance (m, > 0): a fruit may shrink by this much, or grow by this much more
    than growth_mm_per_day allows, and still continue a track."""
    growth_mm_per_day: float = 3.0
    """fastest diameter growth a fruit continues a track with (mm/day, >= 0)."""
    max_missed_dates: int = 1
    """dates (>= 0) a track stays open without an observation (a fruit the detector or the map missed once)."""
    max_shift_m: float = 0.6
    """largest offset (m, > 0) between two dates' row frames along the floor: the robot's different start
    plus the two odometries' drift. The registration searches within it."""
    set_max_diameter_m: float = 0.065
    """a new track counts as a newly set fruit only up to this diameter (m, > 0); a wider one was there
    before and missed (the crop's fruits set at 2-4 cm and grow a few mm a day)."""
    warp_bandwidth_m: float = 0.3
    """length along the row (m, > 0) over which the registration's correction of the rows' different odometry
    drift is smoothed (registration.py): smaller follows faster-changing drift, larger averages more fruits."""
    registration: str = "structure"
    """what each later date is registered on: 'structure' (its stems, leaves and floor, the rows'
    structure.parquet, where it and the dates before it have one, with the fruit pairs that agree; else its
    fruits) or 'fruits' (the fruits' consensus alone, which needs a few fruits that both dates show)."""
    ripen_days: float = 10.0
    """days (>= 0): a green track that ends is lost, not harvested, when the next date came sooner than this
    after its last sighting; later, the fruit may have ripened and been picked. About the crop's time from
    green to picked (sweet pepper: mixed for 3-8 days, picked 4-10 days after red); 0 harvests every ended track."""
    edge_margin_m: float = 0.05
    """the stretch of row a date recorded is its cameras' x range less this margin at each end (m, >= 0);
    set and harvest events are only judged inside it."""

    def __post_init__(self) -> None:
        for name in ("gate_m", "size_tolerance_m", "max_shift_m", "set_max_diameter_m", "warp_bandwidth_m"):
            if not getattr(self, name) > 0:
                raise ValueError(f"track.{name} must be > 0, got {getattr(self, name)}")
        if self.registration not in ("structure", "fruits"):
            raise ValueError(f"track.registration must be 'structure' or 'fruits', got {self.registration!r}")
        for name in ("growth_mm_per_day", "max_missed_dates", "edge_margin_m", "ripen_days"):
            if getattr(self, name) < 0:
                raise ValueError(f"track.{name} must be >= 0, got {getattr(self, name)}")


@dataclass
class DateRows:
    """One recording date of the row: the row's tables the season needs."""

    seq: str
    date: dt.date | None
    day: float
    """days since the season's first date (fractional: from the first frame stamps when they are absolute)."""
    fruits: pd.DataFrame
    """the row's fruits.parquet, counted fruits only: fruit_id, x_m, y_m, z_m, diameter_m, class_name."""
    cameras_xyz: np.ndarray
    """[K, 3] the fused frames' camera positions in the row frame (panoptic_frames)."""
    structure: np.ndarray | None = None
    """[S, 3] the row's static structure in the row frame (structure.parquet voxel means), None if it has none."""


@dataclass
class Season:
    tracks: pd.DataFrame
    """fruit_tracks (schemas/fruit_tracks.py) plus `seq`."""
    summary: pd.DataFrame
    """fruit_track_summary (schemas/fruit_track_summary.py)."""
    dates: pd.DataFrame
    """season_dates (schemas/season_dates.py)."""
    transforms: list[registration.Registration]
    """row frame -> season frame per date, in date order (callable on [N, 3] points)."""
    registered_on: list[str]
    """per date, in date order: 'first date', 'structure' or 'fruits'."""


@dataclass
class _Track:
    obs: list[tuple[int, int]]
    """(date index, row of that date's fruits)."""
    xyz: np.ndarray
    diameter_m: float
    rank: int
    last: int


def stem_side_points(xyz: np.ndarray, diameter_m: np.ndarray, cameras_xyz: np.ndarray) -> np.ndarray:
    """[N, 3] the side of each fruit that faces the plant: half a diameter behind its centre, across the camera
    path (horizontal, perpendicular to the path's main direction, towards the fruits). That side hangs against
    the plant and moves least as the fruit grows (its centre moves out into the aisle by half the growth).
    Used to register and associate dates."""
    if len(cameras_xyz) < 2 or len(xyz) == 0:
        return xyz
    xy = cameras_xyz[:, :2] - cameras_xyz[:, :2].mean(0)
    along = np.linalg.svd(xy, full_matrices=False)[2][0]                # main direction of the path
    across = np.array([-along[1], along[0], 0.0])
    if np.mean((xyz - cameras_xyz.mean(0)) @ across) < 0:
        across = -across
    return xyz + 0.5 * np.nan_to_num(diameter_m)[:, None] * across


def _ranks(names: pd.Series) -> np.ndarray:
    return np.array([RIPENESS_RANK.get(str(n), 0) for n in names], np.int64)


def track_season(dates: list[DateRows], cfg: Config) -> Season:
    """Link the fruits of `dates` (any order; sorted by day here) into tracks."""
    dates = sorted(dates, key=lambda r: r.day)
    gates = association.Gates(cfg.gate_m, cfg.size_tolerance_m, cfg.growth_mm_per_day / 1000)
    tracks: list[_Track] = []
    transforms, regs, how = [], [], []
    positions = []
    fixed_structure: list[np.ndarray] = []   # the structure of the dates so far, in the season frame
    for k, row in enumerate(dates):
        f = row.fruits.reset_index(drop=True)
        centres = f[["x_m", "y_m", "z_m"]].to_numpy(np.float64)
        d = f["diameter_m"].to_numpy(np.float64)
        xyz = stem_side_points(centres, d, row.cameras_xyz)
        rank = _ranks(f["class_name"])
        open_ = [t for t in tracks if k - t.last - 1 <= cfg.max_missed_dates]
        reg, on = _register(row, k, xyz, d, open_, fixed_structure, cfg)
        how.append(on)
        if row.structure is not None and len(row.structure):
            fixed_structure.append(reg(row.structure))
        transforms.append(reg)
        regs.append(reg)
        reg_xyz = reg(xyz)
        positions.append(reg(centres))

        def cost_of(ts: list[_Track], js: list[int], g: association.Gates) -> np.ndarray:
            days = np.array([row.day - dates[t.last].day for t in ts])
            return association.costs(np.array([t.xyz for t in ts]).reshape(-1, 3), np.array([t.diameter_m for t in ts]),
                                     np.array([t.rank for t in ts]), days, reg_xyz[js], d[js], rank[js], g)

        pairs = [(open_[i], j) for i, j in association.assign(cost_of(open_, list(range(len(f))), gates))]
        # only ripe fruits are picked: a track not yet red left without a fruit takes the fruit left over at its
        # place that it could have grown into, however fast (a young fruit can outgrow growth_mm_per_day)
        matched, taken = {id(t) for t, _ in pairs}, {j for _, j in pairs}
        left = [t for t in open_ if id(t) not in matched and t.rank < RIPENESS_RANK[RED]]
        spare = [j for j in range(len(f)) if j not in taken]
        if left and spare:
            free = association.Gates(cfg.gate_m, LEFTOVER_SHRINK * cfg.size_tolerance_m, np.inf)
            more = [(left[a], spare[b]) for a, b in association.assign(cost_of(left, spare, free))]
            pairs += more
            taken |= {j for _, j in more}
        for t, j in pairs:
            t.obs.append((k, j))
            t.xyz, t.last = reg_xyz[j], k
            t.diameter_m = d[j] if np.isfinite(d[j]) else t.diameter_m
            t.rank = max(t.rank, rank[j])
        for j in range(len(f)):
            if j not in taken:
                tracks.append(_Track([(k, j)], reg_xyz[j], d[j], int(rank[j]), k))
    stretches = []
    for row, t in zip(dates, transforms):
        cx = t(row.cameras_xyz)[:, 0] if len(row.cameras_xyz) else np.zeros(0)
        stretches.append((cx.min() + cfg.edge_margin_m, cx.max() - cfg.edge_margin_m) if len(cx) else (np.inf, -np.inf))
    return _tables(dates, tracks, positions, stretches, transforms, regs, how, cfg)


def _register(row: DateRows, k: int, xyz: np.ndarray, d: np.ndarray, open_: list[_Track],
              fixed_structure: list[np.ndarray], cfg: Config) -> tuple[registration.Registration, str]:
    """Date k's registration onto the season frame and what it rests on ('first date', 'structure', 'fruits'):
    the fruits' consensus onto the open tracks, then, with cfg.registration 'structure' and enough structure on
    both sides, the structure's (registration.register_structure: it may start from the fruits' result, and
    the fruit pairs that agree join its correction along the row)."""
    if k == 0:
        return registration.IDENTITY, "first date"
    open_xyz = np.array([t.xyz for t in open_]).reshape(-1, 3)
    inlier_m = min(0.02, cfg.gate_m)
    reg = registration.register(xyz, open_xyz, d, np.array([t.diameter_m for t in open_]), cfg.max_shift_m,
                                final_inlier_m=inlier_m, bandwidth_m=cfg.warp_bandwidth_m)
    if cfg.registration != "structure" or row.structure is None or not fixed_structure:
        return reg, "fruits"
    moving = structure.Structure.from_points(row.structure)
    fixed = structure.Structure.from_points(np.concatenate(fixed_structure))
    if min(len(moving), len(fixed)) < structure.MIN_POINTS:
        return reg, "fruits"
    reg, _ = registration.register_structure(moving, fixed, reg, cfg.max_shift_m, cfg.warp_bandwidth_m,
                                             (xyz, open_xyz), inlier_m)
    return registration.agreement(reg, xyz, open_xyz, inlier_m), "structure"


def _inside(x: float, stretch: tuple[float, float]) -> bool:
    return stretch[0] <= x <= stretch[1]


def growth_rate_mm_per_day(day: np.ndarray, diameter_m: np.ndarray) -> float:
    """Least-squares slope of diameter over days, in mm/day (NaN with fewer than 2 dated diameters)."""
    ok = np.isfinite(diameter_m) & np.isfinite(day)
    if ok.sum() < 2 or np.ptp(day[ok]) == 0:
        return float("nan")
    return float(np.polyfit(day[ok], diameter_m[ok], 1)[0] * 1000)


def _tables(dates: list[DateRows], tracks: list[_Track], positions: list[np.ndarray],
            stretches: list[tuple[float, float]], transforms: list[np.ndarray],
            regs: list[registration.Registration], how: list[str], cfg: Config) -> Season:
    rows, summary = [], []
    n = len(dates)
    lost_on = np.zeros(n, np.int64)
    for tid, t in enumerate(sorted(tracks, key=lambda t: (t.obs[0][0], positions[t.obs[0][0]][t.obs[0][1], 0])), 1):
        obs = []
        for k, j in t.obs:
            f = dates[k].fruits.iloc[j]
            obs.append(dict(seq=dates[k].seq, date=dates[k].date, track_id=tid, day=dates[k].day,
                            fruit_id=int(f.fruit_id), diameter_m=float(f.diameter_m), class_name=str(f.class_name),
                            x_m=positions[k][j, 0], y_m=positions[k][j, 1], z_m=positions[k][j, 2], event="present"))
        k0, kl = t.obs[0][0], t.obs[-1][0]
        first = obs[0]
        gone = kl < n - 1 and _inside(obs[-1]["x_m"], stretches[kl + 1])   # not seen where the next date looked
        lost = gone and t.rank < RIPENESS_RANK[PICKED_FROM] and dates[kl + 1].day - dates[kl].day < cfg.ripen_days
        if lost:
            lost_on[kl + 1] += 1
        if (k0 > 0 and _inside(first["x_m"], stretches[k0 - 1]) and np.isfinite(first["diameter_m"])
                and first["diameter_m"] <= cfg.set_max_diameter_m and not (lost and len(obs) == 1)):
            first["event"] = "set"
        harvested = None
        if gone and not lost:
            harvested = dates[kl + 1]
            obs.append(dict(obs[-1], seq=harvested.seq, date=harvested.date, day=harvested.day, fruit_id=None,
                            diameter_m=None, class_name=None, event="harvested"))
        rows += obs
        seen = [o for o in obs if o["event"] != "harvested"]
        day = np.array([o["day"] for o in seen])
        diam = np.array([o["diameter_m"] for o in seen], np.float64)
        red = [o for o in seen if o["class_name"] == RED]
        summary.append(dict(
            track_id=tid, n_dates=len(seen), first_seq=seen[0]["seq"], first_date=seen[0]["date"],
            last_date=seen[-1]["date"], first_day=seen[0]["day"], last_day=seen[-1]["day"],
            set_date=seen[0]["date"] if seen[0]["event"] == "set" else None,
            date_red=red[0]["date"] if red else None,
            days_to_red=red[0]["day"] - seen[0]["day"] if red else np.nan,
            date_harvested=harvested.date if harvested else None,
            day_harvested=harvested.day if harvested else np.nan,
            growth_mm_per_day=growth_rate_mm_per_day(day, diam),
            diameter_first_m=diam[0], diameter_last_m=diam[-1],
            class_first=seen[0]["class_name"], class_last=seen[-1]["class_name"],
            x_m=seen[-1]["x_m"], y_m=seen[-1]["y_m"], z_m=seen[-1]["z_m"]))
    tracks_df = pd.DataFrame(rows, columns=["seq", "date", "track_id", "day", "fruit_id", "diameter_m", "class_name",
                                            "event", "x_m", "y_m", "z_m"])
    tracks_df = tracks_df.astype({"track_id": "int32", "fruit_id": "Int32", "diameter_m": "float64"})
    tracks_df = tracks_df.sort_values(["day", "track_id"], kind="stable").reset_index(drop=True)
    summary_df = pd.DataFrame(summary, columns=SUMMARY_COLUMNS)
    per_date = []
    first_day = tracks_df.groupby("track_id").day.min()
    for k, (row, t, reg) in enumerate(zip(dates, transforms, regs)):
        on = tracks_df[tracks_df.seq == row.seq]
        per_date.append(dict(
            seq=row.seq, date=row.date, day=row.day, fruits=len(row.fruits),
            continued=int((on.fruit_id.notna() & (on.track_id.map(first_day) < row.day)).sum()),
            set=int((on.event == "set").sum()), harvested=int((on.event == "harvested").sum()), lost=int(lost_on[k]),
            registered_on=how[k], registration_inliers=reg.inliers, registration_rms_m=reg.rms_m,
            tx_m=float(t.transform[0, 3]), ty_m=float(t.transform[1, 3]), tz_m=float(t.transform[2, 3]),
            yaw_deg=float(np.degrees(np.arctan2(t.transform[1, 0], t.transform[0, 0]))),
            correction_max_m=float(np.linalg.norm(t(row.cameras_xyz) - registration.apply(t.transform, row.cameras_xyz),
                                                  axis=1).max()) if len(row.cameras_xyz) else 0.0,
            stretch_x_min_m=float(stretches[k][0]), stretch_x_max_m=float(stretches[k][1])))
    return Season(tracks_df, summary_df, pd.DataFrame(per_date), transforms, how)
