"""The whole DAG on a tiny synthetic row, through the CLI, as a user runs it."""
import pandas as pd
import pytest

from pipeline import cli
from pipeline.dag import STAGE_ORDER
from pipeline.runner import Runner

TINY = ["--set", "synth.n_frames=12", "--set", "synth.width=64", "--set", "synth.height=40",
        "--set", "synth.n_labelled=2", "--set", "synth.supersample=1", "--set", "synth.workers=1",
        "--set", "windows.half_width=3", "--set", "nerf_fit.model.steps=20", "--set", "nerf_fit.model.rays_per_step=128",
        "--set", "nerf_fit.model.n_levels=4", "--set", "nerf_fit.model.log2_capacity=12",
        "--set", "nerf_fit.panoptic.steps=20", "--set", "nerf_fit.panoptic.rays_per_frame=64",
        "--set", "nerf_fit.panoptic.frames_per_step=2"]


def active_stages(root) -> list[str]:
    """The stages `pag all` runs with these settings (optional stages such as colmap_poses are off by default)."""
    return [s.name for s in Runner("synth_tiny", root, overrides=TINY[1::2]).active()]


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    root = tmp_path_factory.mktemp("e2e") / "data"
    rc = cli.main(["all", "--seq", "synth_tiny", "--data-root", str(root), "--no-progress", *TINY])
    assert rc == 0
    return root


def test_every_stage_ran_and_wrote_its_outputs(run_dir):
    interim = run_dir / "interim" / "synth_tiny"
    frames = pd.read_parquet(interim / "frames.parquet")
    assert len(frames) == 12 and frames["labelled"].sum() == 2
    assert (pd.read_parquet(interim / "detections_filtered.parquet")["kept"]).any()
    w = pd.read_parquet(interim / "windows.parquet")
    assert w["window_id"].nunique() == 2
    metrics = pd.read_parquet(run_dir / "processed" / "synth_tiny" / "window_metrics.parquet")
    assert list(metrics["status"]) == ["ok", "ok"] and (metrics["val_psnr"] > 5).all()
    assert (metrics["peak_rss_mb"] > 100).all()  # each worker's own peak over its window: torch alone is more
    poses = pd.read_parquet(run_dir / "processed" / "synth_tiny" / "window_poses.parquet")
    assert set(poses["window_id"]) == {0, 1}
    assert (run_dir / metrics["checkpoint_path"].iloc[0]).is_file()
    assert (metrics["panoptic_steps"] == 20).all() and (metrics["n_slots"] > 2).all()
    renders = pd.read_parquet(run_dir / "processed" / "synth_tiny" / "renders.parquet")
    for wid in (0, 1):
        val = w[(w.window_id == wid) & (w.split == "val")].frame_id
        for kind in ("rgb", "depth", "semantic", "instance"):
            listed = renders[(renders.window_id == wid) & (renders.kind == kind)]
            assert set(listed.frame_id) == set(val) and len(listed) == len(val), (wid, kind)
            assert all((run_dir / p).is_file() for p in listed.path), (wid, kind)
    processed = run_dir / "processed" / "synth_tiny"
    assert len(pd.read_parquet(processed / "panoptic_frames.parquet")) > 0
    ev = pd.read_parquet(processed / "evaluation.parquet")
    assert {"pq", "miou", "pq_detector", "count_gt", "count_pred"} <= set(ev.metric)
    assert (processed / "report" / "report.html").is_file()
    for stage in STAGE_ORDER:
        ran = stage in active_stages(run_dir)
        assert (interim / "_manifest" / f"{stage}.json").is_file() == ran, stage
    assert "colmap_poses" not in active_stages(run_dir)
    assert (run_dir / "processed" / "synth_tiny" / "config.resolved.yaml").is_file()


def test_second_run_skips_everything_and_a_change_reruns_downstream(run_dir, capsys):
    assert cli.main(["all", "--seq", "synth_tiny", "--data-root", str(run_dir), "--no-progress", *TINY]) == 0
    err = capsys.readouterr().err
    assert err.count("up to date, skipped") == len(active_stages(run_dir))
    assert cli.main(["windows", "--seq", "synth_tiny", "--data-root", str(run_dir), "--no-progress", *TINY,
                     "--set", "windows.half_width=2"]) == 0
    assert "windows: done" in capsys.readouterr().err


def test_user_errors_are_one_paragraph_and_non_zero(run_dir, capsys):
    assert cli.main(["all", "--seq", "bup20_row3", "--data-root", str(run_dir)]) == 2
    err = capsys.readouterr().err
    assert "sequence 'bup20_row3' not found" in err and "Traceback" not in err
    assert cli.main(["windows", "--seq", "synth_tiny", "--data-root", str(run_dir), "--set", "windows.half_widht=2"]) == 2
    assert "unknown key(s) ['half_widht']" in capsys.readouterr().err


def test_step_profile_splits_the_steps_time_into_groups_and_rates_the_encoding(run_dir, tmp_path):
    from bench import step_profile

    assert step_profile.group_of("_FusedEncodeBackward") == "encoding"
    assert step_profile.group_of("aten::_fused_adam_") == "optimiser"
    assert step_profile.group_of("aten::mm") == "decoders" and step_profile.group_of("aten::zzz") == "other"
    assert step_profile.main(["--seq", "synth_tiny", "--data-root", str(run_dir), "--out", str(tmp_path),
                              "--steps", "4"]) == 0
    df = pd.read_parquet(tmp_path / "step_profile.parquet")
    groups = df[~df.group.str.startswith("op:")]
    assert abs(groups.share.sum() - 1) < 1e-9 and (groups.seconds >= 0).all()
    enc = groups.set_index("group").loc["encoding"]
    assert enc.seconds > 0 and enc.fraction_of_limit > 0  # the kernel ran and the machine's floor was timed
    assert (df.op.dropna().str.len() > 0).all() and len(df[df.group.str.startswith("op:")]) <= 15
    assert step_profile.main(["--seq", "synth_tiny", "--data-root", str(run_dir), "--out", str(tmp_path),
                              "--steps", "8", "--scaling", "1,2", "--rounds", "1"]) == 0
    scaling = pd.read_parquet(tmp_path / "step_threads.parquet").set_index("threads")
    assert list(scaling.index) == [1, 2] and (scaling.median_ms_per_step > 0).all()
    assert scaling.loc[1, "speedup"] == 1.0
