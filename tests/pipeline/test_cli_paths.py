"""What the command line says about where things are: the report under --data-root, the sequences present."""
import shutil
import subprocess
from pathlib import Path

import pytest

from pipeline import cli
from pipeline.runner import PipelineError, Runner

ROOT = Path(__file__).resolve().parents[2]


def test_make_all_prints_no_report_path_of_its_own(tmp_path):
    if shutil.which("make") is None:
        pytest.skip("make not installed")
    res = subprocess.run(["make", "-n", "all", "SEQ=row_a", f"ARGS=--data-root {tmp_path}"], cwd=ROOT,
                         capture_output=True, text=True, check=True)
    # the one report path printed is pag's, under the data root; no path built from the checkout's data/
    assert f"all --seq row_a --data-root {tmp_path}" in res.stdout
    assert "report.html" not in res.stdout


@pytest.mark.parametrize("command", [["all"], ["report"]])
def test_pag_prints_the_report_under_the_data_root(tmp_path, monkeypatch, capsys, command):
    data_root = tmp_path / "elsewhere"
    (data_root / "raw" / "row_a").mkdir(parents=True)

    def fake_run(self, targets=None, force=False):
        report = self.data_root / "processed" / self.seq / "report" / "report.html"
        report.parent.mkdir(parents=True, exist_ok=True)
        report.write_text("<html></html>")
        return []

    monkeypatch.setattr(Runner, "run", fake_run)
    monkeypatch.chdir(tmp_path)
    assert cli.main([*command, "--seq", "row_a", "--data-root", "elsewhere"]) == 0
    want = (data_root / "processed" / "row_a" / "report" / "report.html").resolve()
    assert f"[pag] report: {want}\n" in capsys.readouterr().out


def test_missing_sequence_lists_the_sequences_present_without_hidden_folders(tmp_path):
    for name in ("row_a", "synth_b", ".synth_c.staging-4242", ".cache"):
        (tmp_path / "raw" / name).mkdir(parents=True)
    with pytest.raises(PipelineError, match=r"Sequences present: \['row_a', 'synth_b'\]$"):
        Runner("row_x", data_root=tmp_path, show_progress=False).run(["ingest"])


@pytest.mark.parametrize("bounds, want", [
    (["--to", "colmap_poses"], ["ingest", "depth_filter", "windows"]),
    (["--from", "colmap_poses", "--to", "nerf_fit"], ["nerf_fit"]),
    (["--from", "fruit_count"], ["fruit_count", "evaluate", "report"]),
])
def test_from_and_to_name_places_in_the_stage_order_also_a_stage_the_config_leaves_out(tmp_path, monkeypatch,
                                                                                        bounds, want):
    (tmp_path / "raw" / "row_a").mkdir(parents=True)
    ran = []
    monkeypatch.setattr(Runner, "run", lambda self, targets=None, force=False: ran.extend(targets) or [])
    # a recorded row (no synth) with odometry poses (the default): colmap_poses is not among the active stages
    assert cli.main(["all", "--seq", "row_a", "--data-root", str(tmp_path), "--no-progress", *bounds]) == 0
    assert ran == want
