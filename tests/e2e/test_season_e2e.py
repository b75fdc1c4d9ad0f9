"""A tiny season through the CLI as a user runs it: two dates of a tiny synthetic row, then `pag track`."""
import duckdb
import pandas as pd
import polars as pl
import pyarrow.dataset as ds
import pytest

from pipeline import cli
from test_pipeline_e2e import TINY

DAYS = (0, 7)


@pytest.fixture(scope="module")
def season_dir(tmp_path_factory):
    root = tmp_path_factory.mktemp("season") / "data"
    for day in DAYS:
        rc = cli.main(["all", "--seq", f"synth_season_d{day:02d}", "--data-root", str(root), "--no-progress", *TINY,
                       "--set", "synth.n_frames=16", "--set", f"synth.day={day}", "--set", "synth.fruits_per_m=16"])
        assert rc == 0
    rc = cli.main(["track", "--data-root", str(root), "--seqs", *[f"synth_season_d{d:02d}" for d in DAYS]])
    assert rc == 0
    return root / "processed" / "_season"


def test_track_writes_the_season_dataset(season_dir):
    parts = sorted(p.parent.name for p in season_dir.glob("fruit_tracks/seq=*/part-0.parquet"))
    assert parts == [f"seq=synth_season_d{d:02d}" for d in DAYS]
    tracks = pd.read_parquet(season_dir / "fruit_tracks")
    assert {"date", "track_id", "day", "fruit_id", "diameter_m", "class_name", "event", "seq"} <= set(tracks.columns)
    assert set(tracks.event) <= {"set", "present", "harvested"}
    assert sorted(tracks.day.unique()) == [0.0, 7.0]
    assert (pd.to_datetime(tracks.date).dt.date.nunique()) == 2
    summary = pd.read_parquet(season_dir / "fruit_track_summary.parquet")
    assert set(summary.track_id) == set(tracks.track_id)
    dates = pd.read_parquet(season_dir / "season_dates.parquet")
    assert list(dates.seq) == [f"synth_season_d{d:02d}" for d in DAYS] and dates.tx_m.iloc[0] == 0.0
    scores = pd.read_parquet(season_dir / "season_scores.parquet").set_index("metric").value
    for m in ("association_precision", "idf1", "event_f1", "registration_error_median_m", "tracking_cost_share"):
        assert m in scores.index
    assert 0 < scores["tracking_cost_share"] < 0.05
    assert (season_dir / "report.html").stat().st_size > 10_000


def test_the_tables_read_without_this_project(season_dir):
    n = duckdb.sql(f"select count(*) from read_parquet('{season_dir}/fruit_tracks/**/*.parquet', "
                   "hive_partitioning = true)").fetchone()[0]
    assert n == len(pd.read_parquet(season_dir / "fruit_tracks")) > 0
    df = pl.read_parquet(f"{season_dir}/fruit_tracks/**/*.parquet", hive_partitioning=True)
    assert "seq" in df.columns and df.height == n
    field = ds.dataset(season_dir / "fruit_tracks", format="parquet", partitioning="hive").schema.field("diameter_m")
    assert field.metadata[b"unit"] == b"m"


def test_track_errors_are_one_paragraph(season_dir, capsys):
    root = season_dir.parent.parent
    assert cli.main(["track", "--data-root", str(root), "--seqs", "synth_season_d00"]) == 2
    assert "at least two dates" in capsys.readouterr().err
    assert cli.main(["track", "--data-root", str(root), "--seqs", "synth_season_d00", "nope"]) == 2
    assert "pag all --seq nope" in capsys.readouterr().err
    assert cli.main(["track", "--data-root", str(root), "--seqs", "synth_season_d00", "synth_season_d07",
                     "--set", "track.gate=1"]) == 2
    assert "gate_m" in capsys.readouterr().err
