"""Scores of a tracked season against a synthetic season's ground truth (gt/fruits.parquet and gt/season.parquet
of every date: fruit_id is the season identity).

Each date's counted fruits are first matched to that date's ground-truth fruits (near row, seen in at least
MIN_FRAMES_VISIBLE frames) in the world frame, as evaluate matches them (stages/evaluate.py); the scores
then ask whether the tracks link the same true fruit:

- association precision / recall over consecutive dates: a link is a track's observations on two
  consecutive dates; it is right when both ends match one true fruit. Precision over links whose ends both
  match a true fruit; recall over true fruits matched on both dates;
- IDF1 over the season: 2 IDTP / (true observations + predicted observations), IDTP from the best one-to-one
  pairing of tracks and true fruits (Ristani et al. 2016);
- registration error: at each matched fruit of a later date, the distance between where the registration
  puts it in the season frame and where the ground truth does (its true world position taken into the
  first date's row frame through the first date's fused camera nearest it);
- growth-rate error: per track whose observations match one true fruit on >= 2 dates, |slope of the
  measured diameters - slope of the true diameters on the same dates|, in mm/week;
- event F1: harvested and set events per consecutive pair of dates against the true ones of fruits inside
  both dates' true recorded stretch (true camera x range less the tracker's edge margin);
- each wrong or missed event, put down to the rows or to the tracker (`<event>_errors_row`,
  `<event>_errors_tracker`): a row error is a fruit a date's map lacks or adds where the event needs it (a
  set fruit not counted on its date; a new track of a fruit counted on no earlier date although it was in
  view, or of no true fruit; a harvested fruit not counted on the date before; a harvest called for a fruit
  still in view but not counted, or for a track that ends on no true fruit); a tracker error is any other
  (the fruits were counted and the linking or the event rules were wrong).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd
from scipy.optimize import linear_sum_assignment

from rowmap.season.tracks import DateRows, Season, growth_rate_mm_per_day

MIN_FRAMES_VISIBLE = 3
"""A true fruit is in a date's population when near-row and visible in at least this many frames."""


@dataclass
class GtDate:
    """One date's ground truth and the row's placement in the world frame."""

    day: float
    """the synthetic day (synth.day)."""
    fruits: pd.DataFrame
    """gt/fruits.parquet of the date."""
    season: pd.DataFrame | None
    """gt/season.parquet of the date (None on day 0)."""
    world_xyz: np.ndarray
    """[F, 3] the date's counted fruits (DateRows.fruits order) in the world frame (evaluate's local alignment)."""
    rel: np.ndarray
    """[K, 4, 4] per fused frame: row frame -> world (T_gt T_map^-1)."""
    cam_x_world: np.ndarray
    """[K] true camera x of those frames."""
    true_cam_x: np.ndarray
    """[N] true camera x of every frame of the recording."""


def _f1(tp: int, fp: int, fn: int) -> float:
    return 2 * tp / (2 * tp + fp + fn) if tp + fp + fn else float("nan")


def _population(g: pd.DataFrame) -> pd.DataFrame:
    return g[g.near_row.astype(bool) & (g.n_frames_visible >= MIN_FRAMES_VISIBLE)].set_index("fruit_id")


def score(season: Season, dates: list[DateRows], gts: list[GtDate], match_max_m: float,
          edge_margin_m: float) -> dict[str, float]:
    """Scores (metric -> value) of `season` made from `dates` (in the season's order) with ground truth `gts`."""
    from rowmap.ground_truth import match_fruits

    n = len(dates)
    pops = [_population(g.fruits) for g in gts]
    to_gt: list[dict[int, int]] = []
    for row, g, pop in zip(dates, gts, pops):
        m = match_fruits(g.world_xyz, pop[["x_m", "y_m", "z_m"]].to_numpy(np.float64), match_max_m)
        to_gt.append({int(row.fruits.fruit_id.iloc[i]): int(pop.index[j]) for i, j, _ in m})
    tr = season.tracks
    obs = tr[tr.fruit_id.notna()].copy()
    k_of = {r.seq: k for k, r in enumerate(dates)}
    obs["k"] = obs.seq.map(k_of)
    obs["true_id"] = [to_gt[k].get(int(f), -1) for k, f in zip(obs.k, obs.fruit_id)]
    out: dict[str, float] = {"dates": float(n), "tracks": float(tr.track_id.nunique()),
                             "fruits_matched": float((obs.true_id >= 0).sum()), "fruits": float(len(obs))}
    # association over consecutive dates
    right = links = true_links = found = 0
    by_track = {t: g.set_index("k").true_id for t, g in obs.groupby("track_id")}
    for k in range(n - 1):
        for gt_ids in by_track.values():
            if k in gt_ids.index and k + 1 in gt_ids.index and gt_ids[k] >= 0 and gt_ids[k + 1] >= 0:
                links += 1
                right += int(gt_ids[k] == gt_ids[k + 1])
        both = set(to_gt[k].values()) & set(to_gt[k + 1].values())
        true_links += len(both)
        here = obs[obs.k == k].groupby("true_id").track_id.apply(set)
        there = obs[obs.k == k + 1].groupby("true_id").track_id.apply(set)
        found += sum(1 for gid in both if here[gid] & there[gid])
    out["association_precision"] = right / links if links else float("nan")
    out["association_recall"] = found / true_links if true_links else float("nan")
    # IDF1
    m = obs[obs.true_id >= 0]
    if len(m):
        tids, gids = np.unique(m.track_id), np.unique(m.true_id)
        co = np.zeros((len(tids), len(gids)))
        np.add.at(co, (np.searchsorted(tids, m.track_id), np.searchsorted(gids, m.true_id)), 1)
        r, c = linear_sum_assignment(-co)
        idtp = co[r, c].sum()
    else:
        idtp = 0.0
    n_gt = sum(len(p) for p in pops)
    out["idf1"] = 2 * idtp / (n_gt + len(obs)) if n_gt + len(obs) else float("nan")
    # registration error at the matched fruits of later dates
    errs = []
    g0 = gts[0]
    inv0 = np.linalg.inv(g0.rel) if len(g0.rel) else np.zeros((0, 4, 4))
    for k in range(1, n):
        row, g = dates[k], gts[k]
        t = season.transforms[k]
        xyz = row.fruits[["x_m", "y_m", "z_m"]].to_numpy(np.float64)
        ids = row.fruits.fruit_id.to_numpy()
        for j in range(len(row.fruits)):
            if int(ids[j]) not in to_gt[k] or not len(inv0):
                continue
            w = g.world_xyz[j]
            f = int(np.abs(g0.cam_x_world - w[0]).argmin())
            truth = inv0[f, :3, :3] @ w + inv0[f, :3, 3]
            errs.append(float(np.linalg.norm(t(xyz[j:j + 1])[0] - truth)))
    out["registration_error_median_m"] = float(np.median(errs)) if errs else float("nan")
    out["registration_error_p90_m"] = float(np.percentile(errs, 90)) if errs else float("nan")
    # growth rate
    gerr = []
    for _, g in m.groupby("track_id"):
        gid = g.true_id.mode().iloc[0]
        g = g[g.true_id == gid]
        if len(g) < 2:
            continue
        true_d = np.array([gts[k].fruits.set_index("fruit_id").diameter_m.get(gid, np.nan) for k in g.k])
        pred = growth_rate_mm_per_day(g.day.to_numpy(np.float64), g.diameter_m.to_numpy(np.float64))
        true = growth_rate_mm_per_day(np.array([gts[k].day for k in g.k]), true_d)
        if np.isfinite(pred) and np.isfinite(true):
            gerr.append(abs(pred - true) * 7)
    out["growth_tracks"] = float(len(gerr))
    out["growth_error_median_mm_per_week"] = float(np.median(gerr)) if gerr else float("nan")
    out.update(_event_scores(season.tracks, obs, dates, gts, pops, to_gt, edge_margin_m))
    return out


def _event_scores(tr: pd.DataFrame, obs: pd.DataFrame, dates: list[DateRows], gts: list[GtDate],
                  pops: list[pd.DataFrame], to_gt: list[dict[int, int]], edge_margin_m: float) -> dict[str, float]:
    """Event counts, F1 and the errors put down to the rows or the tracker (the module docstring); `obs` the
    tracks' observations with their date index `k` and true fruit `true_id` (-1: none), `to_gt` per date the
    counted fruit_id -> true fruit_id, `pops` per date the true population."""
    n = len(dates)
    out: dict[str, float] = {}
    counts = {"harvested": [0, 0, 0], "set": [0, 0, 0]}
    blame = {f"{e}_errors_{w}": 0 for e in ("harvested", "set") for w in ("row", "tracker")}
    counted = [set(m.values()) for m in to_gt]      # per date, the true fruits its map counted
    counted_so_far, seen_so_far = set(), set()    # true fruits counted / in view on dates 0..k
    for k in range(n - 1):
        counted_so_far |= counted[k]
        seen_so_far |= set(pops[k].index)
        a, b = gts[k], gts[k + 1]
        if b.season is None:
            continue
        s = b.season.set_index("fruit_id")
        lo_a, hi_a = a.true_cam_x.min() + edge_margin_m, a.true_cam_x.max() - edge_margin_m
        lo_b, hi_b = b.true_cam_x.min() + edge_margin_m, b.true_cam_x.max() - edge_margin_m
        pa, pb = pops[k], pops[k + 1]
        true_h = {int(i) for i in pa.index if i in s.index and a.day < s.harvest_day.get(i, np.nan) <= b.day
                  and lo_b <= pa.x_m[i] <= hi_b}
        true_s = {int(i) for i in pb.index if i in s.index and a.day < s.set_day.get(i, np.nan) <= b.day
                  and lo_a <= pb.x_m[i] <= hi_a}
        seq_b = dates[k + 1].seq
        pred_h, pred_s = set(), set()
        fp_h = fp_s = 0
        counted_a, counted_b = counted[k], counted[k + 1]
        for tid in tr[(tr.seq == seq_b) & (tr.event == "harvested")].track_id:
            last = obs[(obs.track_id == tid) & (obs.k == k)]
            gid = int(last.true_id.iloc[0]) if len(last) else -1
            if gid in true_h and gid not in pred_h:
                pred_h.add(gid)
            else:
                fp_h += 1
                row = gid < 0 or (gid in pb.index and gid not in counted_b)     # no true fruit, or one missed
                blame["harvested_errors_row" if row else "harvested_errors_tracker"] += 1
        for _, r in tr[(tr.seq == seq_b) & (tr.event == "set")].iterrows():
            gid = to_gt[k + 1].get(int(r.fruit_id), -1)
            if gid in true_s and gid not in pred_s:
                pred_s.add(gid)
            else:
                fp_s += 1
                # no true fruit, or a fruit in view before that no earlier date counted
                row = gid < 0 or (gid in seen_so_far and gid not in counted_so_far)
                blame["set_errors_row" if row else "set_errors_tracker"] += 1
        missed_h, missed_s = true_h - pred_h, true_s - pred_s
        blame["harvested_errors_row"] += len(missed_h - counted_a)
        blame["harvested_errors_tracker"] += len(missed_h & counted_a)
        blame["set_errors_row"] += len(missed_s - counted_b)
        blame["set_errors_tracker"] += len(missed_s & counted_b)
        for key, tp, fp, fn in (("harvested", len(pred_h), fp_h, len(true_h - pred_h)),
                                ("set", len(pred_s), fp_s, len(true_s - pred_s))):
            counts[key][0] += tp
            counts[key][1] += fp
            counts[key][2] += fn
    for key, (tp, fp, fn) in counts.items():
        out[f"{key}_events_true"] = float(tp + fn)
        out[f"{key}_events_pred"] = float(tp + fp)
        out[f"{key}_f1"] = _f1(tp, fp, fn)
    out.update({key: float(v) for key, v in blame.items()})
    tp, fp, fn = (sum(v[i] for v in counts.values()) for i in range(3))
    out["event_f1"] = _f1(tp, fp, fn)
    return out
