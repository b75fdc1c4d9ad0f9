"""Bad input through the whole DAG: a row whose detector found nothing in any frame still gets renders,
a report and an explicit zero count."""
import pandas as pd
import pytest

from pipeline import cli

from test_pipeline_e2e import TINY

pytestmark = pytest.mark.slow  # about 20 s: a second whole-DAG run: `make test-slow`


def test_bad_input_empty_detections_for_the_whole_row(tmp_path, capsys):
    root = tmp_path / "data"
    seq = "synth_nodet"
    rc = cli.main(["all", "--seq", seq, "--data-root", str(root), "--no-progress", *TINY,
                   "--set", "synth.det_miss_rate=1.0", "--set", "synth.det_false_pos_rate=0",
                   "--set", "windows.max_windows=1"])
    assert rc == 0
    err = capsys.readouterr().err
    assert "ingest: no detector segments in the whole row" in err
    assert pd.read_parquet(root / "interim" / seq / "detections.parquet").empty
    counts = pd.read_parquet(root / "processed" / seq / "counts.parquet")
    assert sorted(counts.class_name) == ["fruit_green", "fruit_mixed", "fruit_red"] and (counts["count"] == 0).all()
    renders = list((root / "processed" / seq / "nerf").glob("window_*/renders/rgb_*.png"))
    assert renders and list((root / "processed" / seq / "panoptic" / "instance").glob("*.png"))
    report = (root / "processed" / seq / "report" / "report.html").read_text()
    assert "Total: 0" in report and "no detector segments in the whole row" in report
