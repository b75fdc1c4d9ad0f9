"""rowmap/season on in-memory seasons with known answers: registration, association, events, scores."""
import datetime as dt

import numpy as np
import pandas as pd
import pytest

from rowmap.season import association, registration
from rowmap.season.tracks import Config, DateRows, track_season


def yaw_move(yaw_deg: float, t: tuple[float, float, float]) -> np.ndarray:
    m = np.eye(4)
    c, s = np.cos(np.radians(yaw_deg)), np.sin(np.radians(yaw_deg))
    m[:2, :2] = [[c, -s], [s, c]]
    m[:3, 3] = t
    return m


def world_fruits(rng: np.random.Generator, n: int) -> pd.DataFrame:
    x = np.sort(rng.uniform(-0.2, 2.2, n))
    return pd.DataFrame({"gid": np.arange(n), "x": x, "y": 0.6 + rng.normal(0, 0.03, n), "z": rng.uniform(0.5, 1.0, n),
                         "d": rng.uniform(0.04, 0.09, n), "c": rng.choice(["fruit_green", "fruit_mixed", "fruit_red"], n)})


def as_date(seq: str, day: float, w: pd.DataFrame, world_to_row: np.ndarray, rng: np.random.Generator,
            noise_m: float = 0.003, stretch=(0.0, 2.0)) -> DateRows:
    xyz = registration.apply(world_to_row, w[["x", "y", "z"]].to_numpy()) + rng.normal(0, noise_m, (len(w), 3))
    f = pd.DataFrame({"fruit_id": np.arange(1, len(w) + 1), "x_m": xyz[:, 0], "y_m": xyz[:, 1], "z_m": xyz[:, 2],
                      "diameter_m": w.d.to_numpy() + rng.normal(0, 0.002, len(w)), "class_name": w.c.to_numpy(),
                      "gid": w.gid.to_numpy()})
    cams = registration.apply(world_to_row, np.stack([np.linspace(*stretch, 30), np.zeros(30), np.full(30, 0.75)], 1))
    return DateRows(seq, dt.date(2020, 9, 1) + dt.timedelta(days=int(day)), day, f, cams)


def test_registration_recovers_a_shifted_turned_row_despite_lost_and_new_fruits():
    rng = np.random.default_rng(1)
    w = world_fruits(rng, 30)
    fixed = w[["x", "y", "z"]].to_numpy()
    move = yaw_move(1.5, (0.21, -0.03, 0.01))
    keep = rng.random(30) < 0.6                                        # 40 % harvested
    new = world_fruits(rng, 8)[["x", "y", "z"]].to_numpy()             # set since
    moving_world = np.concatenate([fixed[keep] + rng.normal(0, 0.004, (keep.sum(), 3)), new])
    moving = registration.apply(np.linalg.inv(move), moving_world)    # in the later date's own frame
    d_m = np.concatenate([w.d.to_numpy()[keep] + 0.003, np.full(8, 0.03)])
    reg = registration.register(moving, fixed, d_m, w.d.to_numpy(), max_shift_m=0.6)
    back = reg(moving[:keep.sum()])
    assert np.median(np.linalg.norm(back - fixed[keep], axis=1)) < 0.008
    assert reg.inliers >= 0.8 * keep.sum()
    assert np.degrees(np.arctan2(reg.transform[1, 0], reg.transform[0, 0])) == pytest.approx(1.5, abs=0.5)


def test_registration_without_fruits_is_the_identity():
    reg = registration.register(np.zeros((0, 3)), np.ones((3, 3)), np.zeros(0), np.ones(3), 0.5)
    assert np.array_equal(reg.transform, np.eye(4)) and reg.inliers == 0


def test_association_gates_distance_shrinking_and_ripeness_going_back():
    gates = association.Gates(gate_m=0.05, size_tolerance_m=0.01, growth_m_per_day=0.003)
    tx = np.array([[0.0, 0, 0], [1.0, 0, 0], [2.0, 0, 0], [3.0, 0, 0]])
    c = association.costs(tx, np.array([0.07, 0.07, 0.07, 0.07]), np.array([0, 0, 2, 0]), np.full(4, 7.0),
                          tx + [0.02, 0, 0], np.array([0.075, 0.05, 0.07, 0.12]), np.array([1, 0, 0, 0]), gates)
    assert c[0, 0] == pytest.approx(0.4)                              # 2 cm of 5, grown 5 mm within 21 mm: free
    assert c[1, 1] == association.BLOCKED                              # shrank 2 cm
    assert c[2, 2] == association.BLOCKED                              # red -> green
    assert c[3, 3] == association.BLOCKED                              # grew 5 cm in a week
    assert association.assign(c) == [(0, 0)]


def test_a_season_links_fruits_and_reads_set_and_harvest_events():
    rng = np.random.default_rng(4)
    w0 = world_fruits(rng, 24)
    w0 = w0[(w0.x > 0.1) & (w0.x < 1.9)].reset_index(drop=True)
    picked = w0.index[w0.c == "fruit_red"]
    w1 = w0.drop(picked).assign(d=lambda f: np.where(f.c == "fruit_green", f.d + 0.005, f.d))
    new = pd.DataFrame({"gid": [100, 101], "x": [0.55, 1.45], "y": [0.55, 0.55], "z": [0.62, 0.93], "d": [0.035, 0.04],
                        "c": ["fruit_green", "fruit_green"]})
    w1 = pd.concat([w1, new], ignore_index=True)
    d0 = as_date("a", 0.0, w0, np.eye(4), rng)
    d1 = as_date("b", 7.0, w1, np.linalg.inv(yaw_move(-1.0, (-0.18, 0.02, 0.0))), rng)
    season = track_season([d1, d0], Config())                          # any order in
    t = season.tracks
    assert list(season.dates.seq) == ["a", "b"]
    gid = {("a", int(f)): g for f, g in zip(d0.fruits.fruit_id, d0.fruits.gid)}
    gid.update({("b", int(f)): g for f, g in zip(d1.fruits.fruit_id, d1.fruits.gid)})
    seen = t[t.fruit_id.notna()]
    for _, tr in seen.groupby("track_id"):
        assert len({gid[(s, int(f))] for s, f in zip(tr.seq, tr.fruit_id)}) == 1   # one true fruit per track
    assert seen.track_id.nunique() == len(w0) + 2                      # every kept fruit continued
    harvested = t[t.event == "harvested"]
    assert (harvested.seq == "b").all() and len(harvested) == len(picked)
    sets = t[t.event == "set"]
    assert sorted(gid[("b", int(f))] for f in sets.fruit_id) == [100, 101]
    s = season.summary.set_index("track_id")
    grown = s[(s.n_dates == 2) & (s.class_first == "fruit_green")]
    assert grown.growth_mm_per_day.median() == pytest.approx(5 / 7, abs=0.5)
    assert s.date_harvested.notna().sum() == len(picked)


def test_fruits_outside_the_previous_stretch_are_present_not_set():
    rng = np.random.default_rng(5)
    w = pd.DataFrame({"gid": [0, 1], "x": [0.5, 2.6], "y": [0.6, 0.6], "z": [0.7, 0.7], "d": [0.03, 0.03],
                      "c": ["fruit_green"] * 2})
    d0 = as_date("a", 0.0, w.iloc[:1], np.eye(4), rng, stretch=(0.0, 2.0))
    d1 = as_date("b", 7.0, w, np.eye(4), rng, stretch=(0.6, 2.8))
    t = track_season([d0, d1], Config()).tracks
    assert list(t[t.seq == "b"].event) == ["present", "present"]       # x = 2.6 was never in view on day 0
    assert (t.event != "harvested").all()                              # x = 0.5 is left of day 7's stretch


@pytest.mark.parametrize("name, bad", [("gate_m", 0), ("size_tolerance_m", 0), ("max_shift_m", 0),
                                       ("set_max_diameter_m", 0), ("growth_mm_per_day", -1),
                                       ("max_missed_dates", -1), ("edge_margin_m", -0.1),
                                       ("ripen_days", -1)])
def test_settings_are_checked(name, bad):
    with pytest.raises(ValueError, match=name):
        Config(**{name: bad})


def test_a_fruit_missed_once_continues_its_track_within_max_missed_dates():
    rng = np.random.default_rng(6)
    w = world_fruits(rng, 12)
    w = w[(w.x > 0.1) & (w.x < 1.9)].reset_index(drop=True)
    w["c"] = "fruit_mixed"                                  # ripe enough to be picked: a track that ends is harvested
    dates = [as_date(s, 7.0 * i, w if i != 1 else w.drop(index=[2]), np.eye(4), rng) for i, s in enumerate("abc")]
    keep = track_season(dates, Config(max_missed_dates=1)).tracks
    drop = track_season(dates, Config(max_missed_dates=0)).tracks
    assert keep.track_id.nunique() == len(w) and (keep.event != "harvested").all()
    assert drop.track_id.nunique() == len(w) + 1 and (drop.event == "harvested").sum() == 1


def two_dates(rng, shift=(0.0, 0.0, 0.0), drift_per_m=0.0, grow_m=0.0, new_d=0.04):
    """Day 0 and day 7 of one set of green fruits; day 7's frame shifted and drifting along the row as odometry
    does (x scaled by 1 + drift_per_m, y bent by drift_per_m x^2): no rigid transform undoes it; one new fruit."""
    w = world_fruits(rng, 24)
    w = w[(w.x > 0.1) & (w.x < 1.9)].reset_index(drop=True)
    w["c"] = "fruit_green"
    later = pd.concat([w.assign(d=w.d + grow_m), pd.DataFrame({"gid": [100], "x": [1.0], "y": [0.52], "z": [0.77],
                                                              "d": [new_d], "c": ["fruit_green"]})], ignore_index=True)
    d0 = as_date("a", 0.0, w, np.eye(4), rng, noise_m=0.002)
    d1 = as_date("b", 7.0, later, np.linalg.inv(yaw_move(0.0, shift)), rng, noise_m=0.002)
    xyz = d1.fruits[["x_m", "y_m", "z_m"]].to_numpy()
    d1.fruits[["x_m", "y_m", "z_m"]] = xyz + drift_per_m * np.stack([xyz[:, 0], xyz[:, 0] ** 2, 0 * xyz[:, 0]], 1)
    return w, d0, d1


def test_max_shift_m_bounds_the_offset_the_registration_searches():
    w, d0, d1 = two_dates(np.random.default_rng(7), shift=(0.4, 0.0, 0.0))
    assert track_season([d0, d1], Config(max_shift_m=0.6)).tracks.track_id.nunique() == len(w) + 1
    assert track_season([d0, d1], Config(max_shift_m=0.2)).tracks.track_id.nunique() > len(w) + 5


def test_warp_bandwidth_m_takes_up_drift_a_rigid_transform_cannot():
    w, d0, d1 = two_dates(np.random.default_rng(8), drift_per_m=0.02)
    season = track_season([d0, d1], Config(warp_bandwidth_m=0.3))
    reg = season.transforms[1]
    truth = d0.fruits.set_index("gid")[["x_m", "y_m", "z_m"]]
    f1 = d1.fruits[d1.fruits.gid.isin(truth.index)]
    err = np.linalg.norm(reg(f1[["x_m", "y_m", "z_m"]].to_numpy()) - truth.loc[f1.gid].to_numpy(), axis=1)
    rigid = np.linalg.norm(registration.apply(reg.transform, f1[["x_m", "y_m", "z_m"]].to_numpy())
                           - truth.loc[f1.gid].to_numpy(), axis=1)
    assert np.median(err) < 0.5 * np.median(rigid) and np.median(err) < 0.006
    assert season.dates.correction_max_m.iloc[1] > 0.005
    huge = track_season([d0, d1], Config(warp_bandwidth_m=100.0)).transforms[1]   # one constant correction
    err_huge = np.linalg.norm(huge(f1[["x_m", "y_m", "z_m"]].to_numpy()) - truth.loc[f1.gid].to_numpy(), axis=1)
    assert np.median(err) < np.median(err_huge)


def test_set_max_diameter_m_decides_whether_a_new_fruit_set():
    _, d0, d1 = two_dates(np.random.default_rng(9), new_d=0.05)
    small = track_season([d0, d1], Config(set_max_diameter_m=0.065)).tracks
    strict = track_season([d0, d1], Config(set_max_diameter_m=0.045)).tracks
    assert (small.event == "set").sum() == 1 and (strict.event == "set").sum() == 0


def test_gate_m_and_growth_mm_per_day_decide_what_continues_a_track():
    w, d0, d1 = two_dates(np.random.default_rng(10), grow_m=0.025)           # 25 mm in a week
    n = len(w) + 1
    assert track_season([d0, d1], Config(growth_mm_per_day=3.0)).tracks.track_id.nunique() == n
    assert track_season([d0, d1], Config(gate_m=0.002, growth_mm_per_day=3.0)).tracks.track_id.nunique() > n + 5
    # green fruits are not picked: left without a fruit, they take the one they grew into, however fast
    assert track_season([d0, d1], Config(growth_mm_per_day=1.0)).tracks.track_id.nunique() == n
    # a red fruit gone is picked: a larger fruit where it hung is another one
    for d in (d0, d1):
        d.fruits["class_name"] = "fruit_red"
    assert track_season([d0, d1], Config(growth_mm_per_day=1.0)).tracks.track_id.nunique() > n + 5


def test_a_young_fruit_measured_smaller_than_tolerated_keeps_its_track_unless_another_fruit_takes_it():
    """A green fruit left over after the assignment takes the fruit left over at its place within twice the
    shrink tolerance (diameter noise), never one the assignment gave another track."""
    w, d0, d1 = two_dates(np.random.default_rng(11))
    d1.fruits.loc[d1.fruits.gid == w.gid[3], "diameter_m"] -= 0.015          # measured 15 mm smaller
    t = track_season([d0, d1], Config(size_tolerance_m=0.01)).tracks
    fid = int(d1.fruits.fruit_id[d1.fruits.gid == w.gid[3]].iloc[0])
    track = t[(t.seq == "b") & (t.fruit_id == fid)].track_id.iloc[0]
    assert (t.track_id == track).sum() == 2 and (t.event != "harvested").all()
    d1.fruits.loc[d1.fruits.gid == w.gid[3], "diameter_m"] -= 0.015          # 30 mm: another fruit
    t = track_season([d0, d1], Config(size_tolerance_m=0.01)).tracks
    assert t.track_id.nunique() == len(w) + 2                                 # the new fruit, and this one anew
    assert (t.event != "harvested").all()     # the green track left behind is lost: green fruits are not picked


def test_correction_follows_and_continues_the_drift_of_the_pairs():
    c = registration.correction(np.array([0.5, 1.5]), np.array([0.0, 1.0]), np.array([[0, 0, 0], [0.02, 0, 0.0]]), 0.3)
    np.testing.assert_allclose(c[:, 0], [0.0092, 0.0194], atol=2e-4)   # the docstring's example
    assert np.all(registration.correction(np.array([0.3]), np.zeros(0), np.zeros((0, 3)), 0.3) == 0)


def test_the_plant_side_of_a_growing_fruit_stays_put():
    from rowmap.season.tracks import stem_side_points

    cams = np.stack([np.linspace(0, 1.5, 20), np.full(20, 0.01), np.full(20, 0.75)], 1)
    stem_y = 0.65
    d = np.array([0.04, 0.08])
    centres = np.array([[0.7, stem_y - 0.5 * d[0], 0.8], [0.7, stem_y - 0.5 * d[1], 0.8]])  # pushed off the stem
    side = stem_side_points(centres, d, cams)
    np.testing.assert_allclose(side[:, 1], stem_y, atol=1e-3)
    np.testing.assert_allclose(side[:, [0, 2]], centres[:, [0, 2]], atol=1e-3)


def test_event_errors_are_put_down_to_the_rows_or_to_the_tracker():
    """A three-date season with known misses: fruit 2 missed once (its track continues, no event), set fruit 5
    not counted on its date (set missed, then a wrong set: the row's), a false fruit 9 (a wrong set: the row's),
    fruit 7 missed on the last date (a wrong harvest: the row's), fruit 8 measured 3 cm smaller on the last
    date, more than the tracker lets a track shrink (a wrong set and a wrong harvest: the tracker's)."""
    from rowmap.season.scoring import GtDate, score

    xs = {1: 0.30, 2: 0.47, 3: 0.71, 4: 0.86, 5: 1.12, 6: 1.27, 7: 1.55, 8: 1.74}   # uneven: one consensus
    set_day = {1: 0, 2: 0, 3: 0, 4: 3, 5: 4, 6: 10, 7: 0, 8: 0}
    season = pd.DataFrame({"fruit_id": list(xs), "set_day": [float(set_day[i]) for i in xs],
                           "harvest_day": [5.0 if i == 3 else np.nan for i in xs]})
    in_view = {0: [1, 2, 3, 7, 8], 7: [1, 2, 4, 5, 7, 8], 14: [1, 2, 4, 5, 6, 7, 8]}
    counted = {0: [1, 2, 3, 7, 8], 7: [1, 4, 7, 8], 14: [1, 2, 4, 5, 6, 8, 9]}
    cams = np.stack([np.linspace(0.0, 2.0, 30), np.zeros(30), np.full(30, 0.75)], 1)
    dates, gts = [], []
    for day in (0, 7, 14):
        where = {i: np.array([xs.get(i, 1.63), 0.6 if i != 9 else 0.8, 0.8]) for i in counted[day]}
        xyz = np.array([where[i] for i in counted[day]])
        d = [0.03 if set_day.get(i, day) > 0 else 0.02 if (i, day) == (8, 14) else 0.05 for i in counted[day]]
        names = ["fruit_red" if i in (3, 7) else "fruit_mixed" if i == 8 else "fruit_green" for i in counted[day]]
        fruits = pd.DataFrame({"fruit_id": counted[day], "x_m": xyz[:, 0], "y_m": xyz[:, 1], "z_m": xyz[:, 2],
                               "diameter_m": d, "class_name": names})
        dates.append(DateRows(f"d{day}", dt.date(2020, 9, 1) + dt.timedelta(days=day), float(day), fruits, cams))
        g = pd.DataFrame({"fruit_id": in_view[day], "x_m": [xs[i] for i in in_view[day]], "y_m": 0.6, "z_m": 0.8,
                          "near_row": True, "n_frames_visible": 10, "diameter_m": 0.05})
        gts.append(GtDate(float(day), g, season if day else None, xyz, np.repeat(np.eye(4)[None], 30, 0),
                          cams[:, 0], cams[:, 0]))
    s = track_season(dates, Config())
    out = score(s, dates, gts, match_max_m=0.05, edge_margin_m=0.05)
    # sets: 4 and 6 found; 5 missed on day 7 (not counted), 5 on day 14, 9 and 8 called set wrongly
    assert (out["set_events_true"], out["set_events_pred"]) == (3, 5)
    assert (out["set_errors_row"], out["set_errors_tracker"]) == (3, 1)
    # harvests: 3 found; 7 (missed on the last date) and 8 (its track left behind) called wrongly
    assert (out["harvested_events_true"], out["harvested_events_pred"]) == (1, 3)
    assert (out["harvested_errors_row"], out["harvested_errors_tracker"]) == (1, 1)
    for event in ("set", "harvested"):
        true, pred = out[f"{event}_events_true"], out[f"{event}_events_pred"]
        errors = out[f"{event}_errors_row"] + out[f"{event}_errors_tracker"]
        tp = (true + pred - errors) / 2                                     # errors = false + missed events
        assert out[f"{event}_f1"] == pytest.approx(2 * tp / (true + pred))


def test_a_green_track_that_ends_is_lost_neither_harvested_nor_set_after_one_sighting():
    """Growers pick ripe fruits: a track that ends before it was seen mixed or red is lost (a false fruit or one
    the later dates miss). A red fruit that goes is harvested; a new fruit seen on two dates set."""
    rng = np.random.default_rng(8)
    w = world_fruits(rng, 14)
    w = w[(w.x > 0.1) & (w.x < 1.9)].reset_index(drop=True)
    w["c"] = "fruit_green"
    w.loc[0, "c"] = "fruit_red"
    young = pd.DataFrame({"gid": [100, 101], "x": [0.95, 1.35], "y": [0.55, 0.55], "z": [0.62, 0.93],
                          "d": [0.035, 0.035], "c": ["fruit_green", "fruit_green"]})
    b = pd.concat([w, young], ignore_index=True)                 # 100 a false fruit (b only), 101 a new one
    c = pd.concat([w.drop(index=[0, 1]), young[young.gid == 101]], ignore_index=True)   # red 0 picked, green 1 lost
    dates = [as_date(s, 7.0 * i, f, np.eye(4), rng) for i, (s, f) in enumerate(zip("abc", [w, b, c]))]
    season = track_season(dates, Config())
    t = season.tracks
    assert list(season.dates.lost) == [0, 0, 2] and list(season.dates.harvested) == [0, 0, 1]
    gid = {(d.seq, int(f)): g for d in dates for f, g in zip(d.fruits.fruit_id, d.fruits.gid)}
    first = t[t.fruit_id.notna()].groupby("track_id").first()
    events = {gid[(r.seq, int(r.fruit_id))]: set(t[t.track_id == tid].event) for tid, r in first.iterrows()}
    assert events[w.gid[0]] == {"present", "harvested"}
    assert events[w.gid[1]] == {"present"}
    assert events[100] == {"present"} and events[101] == {"set", "present"}


def test_ripen_days_a_green_fruit_gone_after_a_longer_interval_was_picked():
    """A green fruit gone a week later was not picked (lost); gone two weeks later it may have ripened and been
    picked in between (harvested), with ripen_days between the two intervals."""
    rng = np.random.default_rng(11)
    w = world_fruits(rng, 14)
    w = w[(w.x > 0.1) & (w.x < 1.9)].reset_index(drop=True)
    w["c"] = "fruit_green"

    def season(step_days: float, cfg: Config):
        dates = [as_date(s, step_days * i, f, np.eye(4), np.random.default_rng(12))
                 for i, (s, f) in enumerate(zip("ab", [w, w.drop(index=[3])]))]
        return track_season(dates, cfg).dates

    week, fortnight = season(7.0, Config(ripen_days=10.0)), season(14.0, Config(ripen_days=10.0))
    assert (list(week.lost), list(week.harvested)) == ([0, 1], [0, 0])
    assert (list(fortnight.lost), list(fortnight.harvested)) == ([0, 0], [0, 1])
    assert list(season(14.0, Config(ripen_days=20.0)).lost) == [0, 1]
