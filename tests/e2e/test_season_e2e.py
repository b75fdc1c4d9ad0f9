"""A tiny season through the CLI as a user runs it: dates of a tiny synthetic row, then `pag track`.

The fast tests track ground-truth fruits of tiny rows (`pag bench season --oracle`: synth and ingest run, the
NeRF stages are replaced by the ground truth with noise); the slow one runs the whole DAG on two dates."""
import duckdb
import pandas as pd
import polars as pl
import pyarrow.dataset as ds
import pytest

from pipeline import cli
from test_pipeline_e2e import TINY

DAYS = (0, 7, 14)
SYNTH = ["--set", "synth.n_frames=24", "--set", "synth.width=64", "--set", "synth.height=40", "--set", "synth.n_labelled=2",
         "--set", "synth.supersample=1", "--set", "synth.workers=1", "--set", "synth.write_bag=false"]


@pytest.fixture(scope="module")
def oracle(tmp_path_factory):
    root = tmp_path_factory.mktemp("season") / "data"
    out = root.parent / "bench"
    rc = cli.main(["bench", "season", "--oracle", "--days", *map(str, DAYS), "--seeds", "3", "--data-root", str(root),
                   "--out", str(out), *SYNTH])
    assert rc == 0
    return root, out


def test_bench_season_scores_the_tracks(oracle):
    _, out = oracle
    scores = pd.read_parquet(out / "season_oracle.parquet").set_index("metric").value
    assert scores["dates"] == len(DAYS) and scores["fruits"] > 10
    assert scores["association_precision"] >= 0.9 and scores["association_recall"] >= 0.9
    assert scores["idf1"] >= 0.85
    assert scores["registration_error_median_m"] < 0.02
    assert 0 <= scores["event_f1"] <= 1


def test_track_writes_the_season_dataset(oracle):
    root, _ = oracle
    season_dir = root / "processed" / "_season_season_oracle_s3"
    seqs = [f"synth_season_s3_d{d:02d}" for d in DAYS]
    parts = sorted(p.parent.name for p in season_dir.glob("fruit_tracks/seq=*/part-0.parquet"))
    assert parts == [f"seq={s}" for s in seqs]
    tracks = pd.read_parquet(season_dir / "fruit_tracks")
    assert {"date", "track_id", "day", "fruit_id", "diameter_m", "class_name", "event", "seq"} <= set(tracks.columns)
    assert set(tracks.event) <= {"set", "present", "harvested"}
    assert sorted(tracks.day.unique()) == list(map(float, DAYS))
    assert pd.to_datetime(tracks.date).dt.date.nunique() == len(DAYS)
    summary = pd.read_parquet(season_dir / "fruit_track_summary.parquet")
    assert set(summary.track_id) == set(tracks.track_id) and (summary.n_dates >= 1).all()
    dates = pd.read_parquet(season_dir / "season_dates.parquet")
    assert list(dates.seq) == seqs and dates.tx_m.iloc[0] == 0.0 and (dates.registration_inliers.iloc[1:] > 0).all()
    # each later date rests on the rows' structure (structure.parquet, written with the oracle's fruits)
    assert list(dates.registered_on) == ["first date"] + ["structure"] * (len(DAYS) - 1)
    # a later day starts elsewhere: the registration finds the shift (odometry origins differ)
    assert (dates.tx_m.iloc[1:].abs() > 0.001).all()
    assert (season_dir / "report.html").stat().st_size > 10_000

    # the same folder through `pag track` itself
    assert cli.main(["track", "--data-root", str(root), "--seqs", *seqs]) == 0
    again = pd.read_parquet(root / "processed" / "_season" / "fruit_tracks")
    assert len(again) == len(tracks)


def test_the_tables_read_without_this_project(oracle):
    season_dir = oracle[0] / "processed" / "_season_season_oracle_s3"
    n = duckdb.sql(f"select count(*) from read_parquet('{season_dir}/fruit_tracks/**/*.parquet', "
                   "hive_partitioning = true)").fetchall()[0][0]
    assert n == len(pd.read_parquet(season_dir / "fruit_tracks")) > 0
    df = pl.read_parquet(f"{season_dir}/fruit_tracks/**/*.parquet", hive_partitioning=True)
    assert "seq" in df.columns and df.height == n
    field = ds.dataset(season_dir / "fruit_tracks", format="parquet", partitioning="hive").schema.field("diameter_m")
    assert field.metadata[b"unit"] == b"m"


def test_track_errors_are_one_paragraph(oracle, capsys):
    root, _ = oracle
    assert cli.main(["track", "--data-root", str(root), "--seqs", "synth_season_s3_d00"]) == 2
    assert "at least two dates" in capsys.readouterr().err
    assert cli.main(["track", "--data-root", str(root), "--seqs", "synth_season_s3_d00", "nope"]) == 2
    assert "pag all --seq nope" in capsys.readouterr().err
    assert cli.main(["track", "--data-root", str(root), "--seqs", "synth_season_s3_d00", "synth_season_s3_d07",
                     "--set", "track.gate=1"]) == 2
    assert "gate_m" in capsys.readouterr().err
    assert cli.main(["track", "--data-root", str(root), "--seqs", "synth_season_s3_d00@2020-13-01", "x"]) == 2
    assert "YYYY-MM-DD" in capsys.readouterr().err


def test_a_campaign_report_holds_the_season_section(oracle, capsys):
    """The campaign report of a tracked campaign shows the season's figures (pag campaign --track)."""
    import schemas
    from pipeline import campaign_report, season, season_report

    root, _ = oracle
    seqs = [f"synth_season_s3_d{d:02d}" for d in DAYS]
    tracked, scores, _ = season.track(seqs, root, name="_season_report_test")
    page = campaign_report.render(schemas.empty("campaign_rows"), {}, season_report.section(tracked, scores, 3))
    assert "<h2>Season</h2>" in page and page.count("<h3>") >= 4 and page.count("<img") == 3
    assert all(s in page for s in seqs)                     # the dates table names every date
    assert "<h2>Season</h2>" not in campaign_report.render(schemas.empty("campaign_rows"), {})
    # a tracked campaign of one row is refused before anything runs
    assert cli.main(["campaign", "--seqs", seqs[0], "--track", "--data-root", str(root)]) == 2
    assert "at least two dates" in capsys.readouterr().err


@pytest.mark.slow
def test_a_tiny_season_through_the_whole_dag_as_a_tracked_campaign(tmp_path):
    root = tmp_path / "data"
    seqs = ["synth_season_d00", "synth_season_d07"]
    config = tmp_path / "season.yaml"
    config.write_text("rows:\n" + "".join(f"  {s}: {{synth: {{day: {int(s[-2:])}}}}}\n" for s in seqs))
    assert cli.main(["campaign", "--seqs", *seqs, "--config", str(config), "--data-root", str(root), "--no-progress",
                     "--track", *TINY]) == 0
    season_dir = root / "processed" / "_season"
    scores = pd.read_parquet(season_dir / "season_scores.parquet").set_index("metric").value
    assert 0 < scores["tracking_cost_share"] < 0.05
    dates = pd.read_parquet(season_dir / "season_dates.parquet")
    assert list(dates.seq) == seqs and list(dates.day) == [0.0, 7.0]
    report = (root / "processed" / "_campaign" / "report.html").read_text()
    section = report.split("<h2>Season</h2>")[1]
    assert all(s in section for s in seqs)                  # the dates table of the season section
    tracks = pd.read_parquet(season_dir / "fruit_tracks")     # one partition per date, with no track too
    assert sorted(p.parent.name for p in season_dir.glob("fruit_tracks/seq=*/part-0.parquet")) == [
        f"seq={s}" for s in seqs]
    tracked = len(tracks) > 0                                # tiny fits may count no fruit at all
    assert ("row map by fruit age" in section) == tracked and section.count("<img") == 3 * tracked
