"""The synthetic row on later days of a season: same plants and fruits, grown, ripened, harvested, new ones set."""
import filecmp
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from pipeline.stage import StageContext
from stages import synth
from synthetic import season

TINY = dict(n_frames=8, width=64, height=36, n_labelled=2, workers=1)


def make(root: Path, name: str, **kw) -> Path:
    out = root / name
    out.mkdir()
    ctx = StageContext(stage="synth", seq="row", data_root=root, staging={"raw": out}, show_progress=False)
    synth.run({}, synth.Config(**{**TINY, **kw}), ctx)
    return out


@pytest.fixture(scope="module")
def days(tmp_path_factory):
    root = tmp_path_factory.mktemp("season")
    return {d: make(root, f"d{d}", day=float(d)) for d in (0, 7)}


def files(root: Path) -> list[Path]:
    return sorted(p.relative_to(root) for p in root.rglob("*") if p.is_file())


def test_day_zero_is_the_row_as_it_always_was(days, tmp_path):
    default = make(tmp_path, "default")
    assert files(default) == files(days[0])
    assert "gt/season.parquet" not in {str(p) for p in files(default)}
    _, mismatch, errors = filecmp.cmpfiles(default, days[0], [str(p) for p in files(default)], shallow=False)
    assert mismatch == [] and errors == []
    assert "day" not in yaml.safe_load((default / "gt" / "synth_config.yaml").read_text())


def test_a_week_later_the_same_fruits_have_grown_ripened_or_gone(days):
    f0 = pd.read_parquet(days[0] / "gt" / "fruits.parquet").set_index("fruit_id")
    f7 = pd.read_parquet(days[7] / "gt" / "fruits.parquet").set_index("fruit_id")
    s7 = pd.read_parquet(days[7] / "gt" / "season.parquet").set_index("fruit_id")
    both = f0.index.intersection(f7.index)
    assert len(both) > 0.3 * len(f0)
    assert (f7.loc[both, "diameter_m"] >= f0.loc[both, "diameter_m"] - 1e-4).all()  # never shrinks
    assert (f7.loc[both, "diameter_m"] > f0.loc[both, "diameter_m"] + 1e-3).any()   # green ones grow
    assert (f7.loc[both, "class_id"] >= f0.loc[both, "class_id"]).all()             # green -> mixed -> red
    assert (f7.loc[both, "near_row"] == f0.loc[both, "near_row"]).all()
    moved = np.linalg.norm(f7.loc[both, ["x_m", "y_m", "z_m"]].to_numpy() - f0.loc[both, ["x_m", "y_m", "z_m"]].to_numpy(), axis=1)
    assert moved.max() < 0.03                                                        # pushed off the stem as it grows
    gone = f0.index.difference(f7.index)
    assert len(gone) and s7.loc[gone, "harvest_day"].between(0, 7).all() and not s7.loc[gone, "present"].any()
    assert (f0.loc[gone, "class_id"] >= season.MIXED).all()                           # only ripe ones are picked
    new = f7.index.difference(f0.index)
    assert len(new) and new.min() > f0.index.max()                                   # new ids after day 0's
    assert s7.loc[new, "set_day"].between(0, 7).all() and (f7.loc[new, "diameter_m"] < 0.05).all()
    assert (f7.loc[new, "class_id"] == season.GREEN).all()
    assert set(s7.index) == set(f0.index) | set(new) and (s7.present == s7.index.isin(f7.index)).all()


def test_a_later_day_is_recorded_later_from_another_start(days):
    odo0, odo7 = (pd.read_csv(days[d] / "odometry.csv") for d in (0, 7))
    assert odo7.timestamp.iloc[0] - odo0.timestamp.iloc[0] == 7 * 86_400 * 10**9
    assert odo7[["tx", "ty"]].iloc[0].abs().max() < 1e-9                            # its own origin
    p0, p7 = (pd.read_parquet(days[d] / "gt" / "poses.parquet") for d in (0, 7))
    assert 1e-3 < abs(p7.tx.iloc[0] - p0.tx.iloc[0]) <= synth.START_SHIFT_M
    assert p7.stamp_ns.iloc[0] == synth.FIRST_STAMP_NS + 7 * 86_400 * 10**9


def test_growth_rate_scale_speeds_growth():
    lives = [season.life_on_plant(season.GREEN, 0.07, np.random.default_rng(3), s) for s in (1.0, 2.0)]
    assert lives[0].diameter_m(0) == lives[1].diameter_m(0) == 0.07
    assert lives[1].diameter_m(7) > lives[0].diameter_m(7) > 0.07
    assert lives[0].diameter_m(1e4) == pytest.approx(lives[1].diameter_m(1e4))
    assert lives[0].diameter_m(1e4) <= season.MAX_DIAMETER_M
    with pytest.raises(ValueError, match="growth_rate_scale"):
        synth.Config(growth_rate_scale=0)


def test_fruit_set_rate_sets_new_fruits(tmp_path):
    none = make(tmp_path, "none", day=7.0, fruit_set_per_m_per_week=0.0)
    many = make(tmp_path, "many", day=7.0, fruit_set_per_m_per_week=6.0)
    s_none, s_many = (pd.read_parquet(p / "gt" / "season.parquet") for p in (none, many))
    assert s_none.set_day.notna().sum() == 0
    assert s_many.set_day.notna().sum() > 5
    with pytest.raises(ValueError, match="fruit_set_per_m_per_week"):
        synth.Config(fruit_set_per_m_per_week=-1)
    with pytest.raises(ValueError, match="day"):
        synth.Config(day=-1)


def test_ripening_order_and_harvest_follow_each_life():
    rng = np.random.default_rng(0)
    for klass in (season.GREEN, season.MIXED, season.RED):
        life = season.life_on_plant(klass, 0.08, rng, 1.0)
        assert life.class_id(0) == klass and life.present(0)
        assert life.t_mixed_day < life.t_red_day < life.t_harvest_day
        assert not life.present(life.t_harvest_day)
    new = season.life_of_new_fruit(3.0, rng, 1.0)
    assert not new.present(2.9) and new.present(3.0) and new.class_id(3.0) == season.GREEN
    assert 0.025 <= new.diameter_m(3.0) <= 0.035 < new.diameter_m(17.0)
