"""Which code made an output and what it cost: manifest records read back per stage, and the report's table."""
import json

import numpy as np

from pipeline.provenance import stage_costs
from pipeline.stage import StageContext
from stages import report


def _manifest(root, seq, stage, **rec):
    d = root / "interim" / seq / "_manifest"
    d.mkdir(parents=True, exist_ok=True)
    (d / f"{stage}.json").write_text(json.dumps({"stage": stage, **rec}))


def test_stage_costs_reads_each_record_and_marks_missing_or_broken_ones(tmp_path):
    _manifest(tmp_path, "r", "ingest", seconds=2.5, peak_rss_mb=700.0, code_version="abc")
    _manifest(tmp_path, "r", "nerf_fit", seconds=100.0, peak_rss_mb=4000.0, code_version="abc")
    (tmp_path / "interim" / "r" / "_manifest" / "windows.json").write_text("{not json")
    df = stage_costs(tmp_path, "r", ["ingest", "windows", "nerf_fit", "evaluate"])
    assert df.stage.tolist() == ["ingest", "windows", "nerf_fit", "evaluate"]
    assert df.seconds.tolist()[0] == 2.5 and df.peak_rss_mb.tolist()[2] == 4000.0
    assert np.isnan(df.seconds[1]) and np.isnan(df.seconds[3]) and df.code_version[3] == ""


def test_report_cost_table_lists_the_stages_that_ran_and_their_total(tmp_path):
    _manifest(tmp_path, "r", "ingest", seconds=2.0, peak_rss_mb=700.0, code_version="abc")
    _manifest(tmp_path, "r", "nerf_fit", seconds=100.0, peak_rss_mb=4000.0, code_version="abc")
    _manifest(tmp_path, "r", "report", seconds=9.0, peak_rss_mb=9999.0, code_version="old")
    page = report.stage_costs_html(StageContext(stage="report", seq="r", data_root=tmp_path))
    assert ">ingest<" in page and ">nerf_fit<" in page and ">windows<" not in page
    assert ">report<" not in page and "9999" not in page          # the running report is not its own cost
    assert ">total<" in page and ">102<" in page and ">4000<" in page
    empty = report.stage_costs_html(StageContext(stage="report", seq="other", data_root=tmp_path))
    assert "No stage records" in empty
