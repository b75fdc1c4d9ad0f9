"""`pag campaign` on two tiny synthetic rows: the rows' outputs, the dataset, the report, skips and failures."""
import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pyarrow.parquet as pq
import pytest
import yaml

from campaign_fixture import SEQS, campaign_args
from pipeline import cli, parallel
from pipeline.classes import DEFAULT_CLASSES

pytestmark = pytest.mark.slow  # about 35 s: three rows fitted for the shared campaign fixture: `make test-slow`


def camp(root: Path) -> Path:
    return root / "processed" / "_campaign"


def test_every_row_ran_with_its_own_settings_and_one_dataset_holds_them(local_campaign):
    root, _ = local_campaign
    for seq in SEQS:
        assert (root / "processed" / seq / "report" / "report.html").is_file()
        for table in ("fruits", "counts", "window_metrics", "evaluation"):
            assert (camp(root) / table / f"seq={seq}" / "part-0.parquet").is_file(), (table, seq)
    # the per-row section of the config file gave each row its own synthetic seed
    seeds = [yaml.safe_load((root / "interim" / seq / "config.resolved.yaml").read_text())["synth"]["seed"]
             for seq in SEQS]
    assert seeds == [1, 2]
    frames = [pd.read_parquet(root / "interim" / seq / "frames.parquet") for seq in SEQS]
    assert not frames[0][["tx", "ty"]].equals(frames[1][["tx", "ty"]])


def test_rows_summary_matches_each_rows_tables(local_campaign):
    root, _ = local_campaign
    rows = pd.read_parquet(camp(root) / "rows.parquet").set_index("seq")
    assert list(rows.index) == list(SEQS) and (rows.status == "ok").all()
    for seq in SEQS:
        counts = pd.read_parquet(root / "processed" / seq / "counts.parquet").set_index("class_name")["count"]
        fruits = pd.read_parquet(root / "processed" / seq / "fruits.parquet")
        metrics = pd.read_parquet(root / "processed" / seq / "window_metrics.parquet")
        ev = pd.read_parquet(root / "processed" / seq / "evaluation.parquet")
        frames = pd.read_parquet(root / "interim" / seq / "frames.parquet")
        r = rows.loc[seq]
        assert r.fruits == counts.sum()
        for c in DEFAULT_CLASSES:
            if c.is_thing:
                assert r[f"count_{c.name}"] == counts.get(c.name, 0)
        steps = frames[["tx", "ty"]].diff().dropna()
        assert abs(r.row_length_m - (steps.tx ** 2 + steps.ty ** 2).pow(0.5).sum()) < 1e-9
        assert abs(r.fruits_per_m - r.fruits / r.row_length_m) < 1e-9
        counted = fruits[fruits.counted]
        if len(counted):
            assert abs(r.mean_diameter_m - counted.diameter_m.mean()) < 1e-12
        assert abs(r.val_psnr - metrics.val_psnr.mean()) < 1e-9
        assert abs(r.pq - ev[(ev.scope == "row") & (ev.metric == "pq")].value.iloc[0]) < 1e-12
        # synthetic stamps start at 2020-09-13 (UTC); these names hold no date
        assert str(r.date) == "2020-09-13" and r.date_source == "first_stamp"
    assert rows.fruits.sum() > 0, "the tiny rows should yield at least one fruit"


READER = r"""
import json, sys
import duckdb, pandas as pd, polars as pl, pyarrow.dataset as ds, pyarrow.parquet as pq


out = {}
fruits = ds.dataset("fruits", format="parquet", partitioning="hive")
out["pyarrow_rows"] = fruits.count_rows()
meta = {k.decode(): v.decode() for k, v in fruits.schema.field("diameter_m").metadata.items()}
out["pyarrow_diameter_meta"] = meta
out["pyarrow_date_type"] = str(fruits.schema.field("date").type)
df = pd.read_parquet("counts")
out["pandas_counts"] = {str(s): int(v) for s, v in df.groupby("seq", observed=True)["count"].sum().items()}
con = duckdb.connect()
out["duckdb_fruits"] = {s: n for s, n in con.execute(
    "SELECT seq, count(*) FROM 'fruits/**/*.parquet' GROUP BY seq ORDER BY seq").fetchall()}
out["duckdb_fruits_hive"] = {s: n for s, n in con.execute(
    "SELECT seq, count(*) FROM read_parquet('fruits/**/*.parquet', hive_partitioning = true) GROUP BY seq").fetchall()}
kv = con.execute("SELECT key, value FROM parquet_kv_metadata('counts/**/*.parquet')").fetchall()
cols = [json.loads(v) for k, v in kv if k == b"pag.columns"][0]
out["duckdb_count_unit"] = cols["count"]["unit"]
out["duckdb_rows"] = con.execute("SELECT seq, fruits, pq FROM 'rows.parquet' ORDER BY seq").fetchall()
pf = pl.read_parquet("window_metrics/**/*.parquet", hive_partitioning=True)
out["polars_windows"] = {s: n for s, n in pf.group_by("seq").len().iter_rows()}
out["polars_schema_has_date"] = str(pf.schema["date"])
out["project_imported"] = sorted(m for m in ("pipeline", "schemas", "stages", "nerf") if m in sys.modules)
print(json.dumps(out))
"""


def test_dataset_reads_in_pandas_pyarrow_duckdb_polars_without_the_project(local_campaign, tmp_path):
    root, _ = local_campaign
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    run = subprocess.run([sys.executable, "-c", READER], cwd=camp(root), env=env, capture_output=True, text=True,
                         timeout=120)
    assert run.returncode == 0, run.stderr
    out = json.loads(run.stdout)
    fruits = {seq: len(pd.read_parquet(root / "processed" / seq / "fruits.parquet")) for seq in SEQS}
    counts = {seq: int(pd.read_parquet(root / "processed" / seq / "counts.parquet")["count"].sum()) for seq in SEQS}
    windows = {seq: len(pd.read_parquet(root / "processed" / seq / "window_metrics.parquet")) for seq in SEQS}
    assert out["pyarrow_rows"] == sum(fruits.values())
    assert out["pyarrow_diameter_meta"]["unit"] == "m" and "spheroid" in out["pyarrow_diameter_meta"]["doc"]
    assert out["pyarrow_date_type"] == "date32[day]"
    assert out["pandas_counts"] == counts
    assert out["duckdb_fruits"] == {s: n for s, n in fruits.items() if n}
    assert out["duckdb_fruits_hive"] == out["duckdb_fruits"]
    assert out["duckdb_count_unit"] == "fruits"
    assert [r[0] for r in out["duckdb_rows"]] == sorted(SEQS) and [r[1] for r in out["duckdb_rows"]] == [
        counts[s] for s in sorted(SEQS)]
    assert out["polars_windows"] == windows and out["polars_schema_has_date"] == "Date"
    assert out["project_imported"] == []


def test_campaign_report_is_one_self_contained_page_linking_each_row(local_campaign):
    root, _ = local_campaign
    page = (camp(root) / "report.html").read_text()
    assert page.count('src="data:image/png;base64,') == 2  # counts per row and class, sizes per row
    assert not re.search(r'src="(?!data:)', page)
    links = re.findall(r'href="([^"]+)"', page)
    assert len(links) == len(SEQS)
    for link, seq in zip(links, SEQS):
        assert (camp(root) / link).resolve() == (root / "processed" / seq / "report" / "report.html").resolve()
        assert (camp(root) / link).is_file()


def test_second_campaign_skips_up_to_date_rows_and_reports_a_failing_row(local_campaign, tmp_path, capsys,
                                                                        monkeypatch):
    src, config = local_campaign

    def no_cluster(*args, **kwargs):
        raise AssertionError("a campaign with nothing to fit started a cluster")

    monkeypatch.setattr(parallel, "client_for", no_cluster)
    root = tmp_path / "data"
    shutil.copytree(src, root)
    before = pq.read_table(camp(root) / "fruits").num_rows
    capsys.readouterr()
    (root / "raw" / "empty_row").mkdir()  # a recorded row's folder with nothing in it: ingest fails
    args = campaign_args(root, config)
    rc = cli.main(args[:2] + [*SEQS, "missing_row", "empty_row"] + args[2 + len(SEQS):])
    err = capsys.readouterr().err
    assert rc == 1
    assert "row missing_row failed" in err and "sequence 'missing_row' not found" in err
    assert "row empty_row failed: stage ingest: " in err
    for seq in SEQS:  # every stage of the finished rows is up to date
        assert re.search(rf"{seq}: ok in [\d.]+ s \(0 stages ran, [1-9]\d* up to date\)", err), err
    assert "nerf_fit: running" not in err
    rows = pd.read_parquet(camp(root) / "rows.parquet").set_index("seq")
    assert rows.loc["missing_row", "status"] == "failed" and "not found" in rows.loc["missing_row", "error"]
    assert rows.loc["empty_row", "error"].startswith("stage ingest: ")
    assert (rows.loc[list(SEQS), "status"] == "ok").all()
    assert pq.read_table(camp(root) / "fruits").num_rows == before
    assert not (camp(root) / "fruits" / "seq=missing_row").exists()
    assert "missing_row" in (camp(root) / "report.html").read_text()
