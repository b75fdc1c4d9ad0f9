"""Progress on stderr: plain lines (no carriage returns) when stderr is not a terminal, throttled per task."""
from __future__ import annotations

import pytest

from pipeline import cli, progress
from pipeline.config import ConfigError, RunConfig


def test_lines_one_per_unit_without_carriage_returns(capsys):
    assert not progress.interactive()  # pytest captures stderr: not a terminal
    list(progress.iterate(range(4), "nerf_fit window 2", interval_s=0, unit="validation render"))
    err = capsys.readouterr().err
    assert "\r" not in err
    lines = err.splitlines()
    assert [ln.split(" (")[0] for ln in lines] == [f"[pag] nerf_fit window 2: validation render {i}/4" for i in range(1, 5)]
    assert all(ln.endswith(" s)") for ln in lines)


def test_lines_are_throttled_but_first_and_last_unit_and_phase_changes_show(capsys):
    t = progress.Tracker("window 0", enabled=True, interval_s=3600, bars=False)
    for i in range(1, 101):
        t.update(i, 100, "step")
    for i in range(1, 4):
        t.update(i, 3, "validation render", {"frame_s": 0.5})
    t.finish("done in 1.0 s")
    lines = capsys.readouterr().err.splitlines()
    assert [ln.split(" (")[0] for ln in lines] == [
        "[pag] window 0: step 1/100", "[pag] window 0: step 100/100",
        "[pag] window 0: validation render 1/3 frame_s=0.5", "[pag] window 0: validation render 3/3 frame_s=0.5",
        "[pag] window 0: done in 1.0 s"]


def test_disabled_progress_prints_nothing(capsys):
    t = progress.Tracker("x", enabled=False, interval_s=0)
    t.update(1, 2, "step")
    t.finish("done")
    assert capsys.readouterr().err == ""


def test_stage_progress_follows_run_progress(tmp_path, capsys):
    tiny = ["--set", "synth.n_frames=4", "--set", "synth.width=32", "--set", "synth.height=24",
            "--set", "synth.n_labelled=1", "--set", "synth.supersample=1", "--set", "synth.workers=1"]
    base = ["synth", "--seq", "synth_p", "--data-root", str(tmp_path), *tiny, "--force"]
    assert cli.main([*base, "--set", "run.progress_interval_s=0"]) == 0
    err = capsys.readouterr().err
    assert all(f"[pag] synth: render and write {i}/4 (" in err for i in range(1, 5)) and "\r" not in err
    for quiet in (["--no-progress"], ["--set", "run.progress=false"]):
        assert cli.main([*base, *quiet]) == 0
        err = capsys.readouterr().err
        assert "render and write" not in err and "[pag] synth: done" in err


def test_interval_must_not_be_negative():
    with pytest.raises(ConfigError, match="progress_interval_s must be >= 0"):
        RunConfig(progress_interval_s=-1)
