"""`pag all` killed with SIGKILL at several points of a tiny row, then rerun: the rerun finishes, reuses
what was complete (a finished NeRF window is not refitted) and ends with the outputs of a run that was
never interrupted. Also: progress reaches a non-terminal stderr as plain lines, renders included.

The kill points are reached deterministically with PAG_HOLD_AT (pipeline/progress.py): the run prints
the progress line naming the point and sleeps there until the test kills its whole process group
(the Dask workers included).
"""
from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch

from pipeline.io import LEFTOVER

pytestmark = pytest.mark.slow  # about 60 s: a row run once whole and three times killed: `make test-slow`

REPO = Path(__file__).resolve().parents[2]
SEQ = "synth_kill"
TINY = ["--set", "synth.n_frames=12", "--set", "synth.width=64", "--set", "synth.height=40",
        "--set", "synth.n_labelled=2", "--set", "synth.supersample=1", "--set", "synth.workers=1",
        "--set", "windows.half_width=3", "--set", "nerf_fit.model.steps=20", "--set", "nerf_fit.model.rays_per_step=128",
        "--set", "nerf_fit.model.n_levels=4", "--set", "nerf_fit.model.log2_capacity=12",
        "--set", "nerf_fit.panoptic.steps=20", "--set", "nerf_fit.panoptic.rays_per_frame=64",
        "--set", "nerf_fit.panoptic.frames_per_step=2",
        # one worker with one thread: windows fit one after the other ("one window done" exists) and a
        # window's result does not depend on how many windows run beside it
        "--set", "nerf_fit.workers=1", "--set", "nerf_fit.threads_per_worker=1",
        "--set", "run.progress_interval_s=0",
        # the ICP pose correction (Open3D) rounds differently from one process to the next (its sums follow
        # memory layout), so two fits of a window agree only to ~1e-16 m; 'scale' is bit-reproducible
        "--set", "nerf_fit.depth_poses=scale"]
TIMING_COLUMNS = {"fit_s", "render_s_per_image", "panoptic_fit_s", "peak_rss_mb"}
RUN_COLUMNS = {"worker"}  # which Dask worker ran a window: an address that differs between any two runs
RUN_LIMIT_S = 240


def pag_all(root: Path, hold: str | None = None) -> tuple[int | None, str]:
    """Run `pag all` as its own process group; with `hold`, kill the group (SIGKILL) once the run holds at
    that progress line. Returns (exit code or None when killed, stderr)."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]))
    env.pop("PAG_HOLD_AT", None)
    if hold:
        env["PAG_HOLD_AT"] = hold
    proc = subprocess.Popen([sys.executable, "-m", "pipeline.cli", "all", "--seq", SEQ, "--data-root", str(root), *TINY],
                            cwd=REPO, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)
    watchdog = threading.Timer(RUN_LIMIT_S, lambda: os.killpg(proc.pid, signal.SIGKILL))
    watchdog.start()
    lines, held = [], False
    try:
        for line in proc.stderr:
            lines.append(line)
            if hold and "holding at" in line:
                held = True
                os.killpg(proc.pid, signal.SIGKILL)
                break
        proc.wait()
    finally:
        watchdog.cancel()
        proc.stderr.close()
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    err = "".join(lines)
    if hold:
        assert held, f"the run never reached {hold!r}:\n{err[-3000:]}"
        with pytest.raises(ProcessLookupError):  # the whole group is gone, Dask workers included
            for _ in range(50):
                os.killpg(proc.pid, 0)
                threading.Event().wait(0.1)
        return None, err
    return proc.returncode, err


def manifests(root: Path) -> set[str]:
    return {p.stem for p in (root / "interim" / SEQ / "_manifest").glob("*.json") if p.stem != "hashcache"}


def leftovers(root: Path) -> list[Path]:
    return [p for p in root.rglob(".*") if LEFTOVER.match(p.name)]


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    root = tmp_path_factory.mktemp("reference") / "data"
    rc, err = pag_all(root)
    assert rc == 0, err[-3000:]
    return root, err


def test_progress_reaches_a_log_as_lines_renders_included(reference):
    root, err = reference
    windows = pd.read_parquet(root / "interim" / SEQ / "windows.parquet")
    assert "\r" not in err
    for i in range(1, 13):
        assert f"[pag] ingest: frames {i}/12 (" in err
    for wid in (0, 1):
        assert f"[pag] nerf_fit window {wid}: step 20/20" in err  # from inside the Dask worker
        assert f"[pag] nerf_fit window {wid}: panoptic step 20/20" in err
        n = int((windows[windows.window_id == wid].split == "val").sum())    # one render per validation frame
        assert n >= 2
        for i in range(1, n + 1):
            assert re.search(rf"\[pag\] nerf_fit window {wid}: panoptic validation render {i}/{n} frame_s=\S+ \(", err)
        assert re.search(rf"\[pag\] nerf_fit window {wid}: done in [\d.]+ s", err)
    for stage, what in (("synth", "render and write"), ("depth_filter", "frames"), ("panoptic_fusion", "read renders"),
                        ("panoptic_fusion", "write fused frames"), ("fruit_count", "unproject fruits"),
                        ("evaluate", "fused frames")):
        assert f"[pag] {stage}: {what} 1/" in err, (stage, what)


def same_tables(a: Path, b: Path, root_a: Path, root_b: Path) -> None:
    """Equal tables, timing and worker columns aside; notes that quote a path name it under their own data
    root (the two runs live in different folders), so each root is replaced by a placeholder first."""
    da, db = pd.read_parquet(a), pd.read_parquet(b)
    drop = sorted((TIMING_COLUMNS | RUN_COLUMNS) & set(da.columns))
    da, db = da.drop(columns=drop), db.drop(columns=drop)
    for df, root in ((da, root_a), (db, root_b)):
        for c in df.columns:
            if pd.api.types.is_string_dtype(df[c]) or df[c].dtype == object:
                df[c] = df[c].map(lambda v: v.replace(str(root), "<root>") if isinstance(v, str) else v).astype(
                    df[c].dtype)
    pd.testing.assert_frame_equal(da, db, check_exact=True, obj=str(a))


def same_state(a, b, where: str) -> None:
    if isinstance(a, dict):
        assert isinstance(b, dict) and a.keys() == b.keys(), where
        for k in a:
            same_state(a[k], b[k], f"{where}.{k}")
    elif isinstance(a, torch.Tensor):
        assert torch.equal(a, b), where
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b)):
            same_state(x, y, f"{where}[{i}]")
    elif isinstance(a, np.ndarray):
        np.testing.assert_array_equal(a, b, err_msg=where)
    else:
        assert a == b or (a != a and b != b), where


def assert_same_outputs(ref: Path, got: Path) -> None:
    """Every table, image and checkpoint of the row equal (timing columns and the report page aside)."""
    compared = 0
    for area in ("interim", "processed"):
        ref_files = sorted(p.relative_to(ref) for p in (ref / area / SEQ).rglob("*")
                           if p.is_file() and "_manifest" not in p.parts and not p.name.startswith("."))
        got_files = sorted(p.relative_to(got) for p in (got / area / SEQ).rglob("*")
                           if p.is_file() and "_manifest" not in p.parts and not p.name.startswith("."))
        assert ref_files == got_files, set(ref_files) ^ set(got_files)
        for rel in ref_files:
            a, b = ref / rel, got / rel
            if rel.suffix == ".parquet":
                same_tables(a, b, ref, got)
            elif rel.suffix == ".pt":
                same_state(torch.load(a, weights_only=False), torch.load(b, weights_only=False), str(rel))
            elif rel.name != "report.html":  # the page quotes the fit times
                assert a.read_bytes() == b.read_bytes(), rel
            compared += 1
    assert compared > 50


def test_runs_killed_at_three_points_resume_and_end_like_an_uninterrupted_run(reference, tmp_path):
    ref_root, _ = reference
    root = tmp_path / "data"
    interim = root / "interim" / SEQ

    # 1. killed during ingest: synth is committed, ingest is not; its staging folder is left behind
    _, err = pag_all(root, hold="ingest: frames 6/12")
    assert manifests(root) == {"synth"}
    assert not (interim / "frames.parquet").exists()
    assert leftovers(root), "a kill during ingest leaves its staging folder"

    # 2. rerun, killed in nerf_fit once window 0 is finished and window 1 has started
    _, err = pag_all(root, hold="nerf_fit window 1: step 1/20")
    assert "[pag] synth: up to date, skipped" in err and "[pag] ingest: done" in err
    assert "left by an interrupted run" in err
    assert manifests(root) == {"synth", "ingest", "depth_filter", "windows"}
    resume = interim / "_resume" / "nerf_fit"
    (key_dir,) = resume.iterdir()
    assert (key_dir / "window_000" / "finished.pkl").is_file()
    assert not (key_dir / "window_001").exists()
    assert not (root / "processed" / SEQ / "nerf").exists()

    # 3. rerun, killed during panoptic_fusion: window 0 is reused, only window 1 is fitted
    _, err = pag_all(root, hold="panoptic_fusion: read renders 3/")
    assert "[pag] nerf_fit window 0: reused" in err
    assert "nerf_fit window 0: step" not in err and "[pag] nerf_fit window 1: step 20/20" in err
    assert "windows_reused=1" in err
    for stage in ("synth", "ingest", "depth_filter", "windows"):
        assert f"[pag] {stage}: up to date, skipped" in err
    assert "nerf_fit" in manifests(root) and "panoptic_fusion" not in manifests(root)
    assert not (interim / "_resume").exists(), "partial work is removed once nerf_fit's outputs are committed"

    # 4. rerun to the end: only what was not committed runs
    rc, err = pag_all(root)
    assert rc == 0, err[-3000:]
    for stage in ("synth", "ingest", "depth_filter", "windows", "nerf_fit"):
        assert f"[pag] {stage}: up to date, skipped" in err
    for stage in ("panoptic_fusion", "fruit_count", "evaluate", "report"):
        assert f"[pag] {stage}: done" in err
    assert leftovers(root) == []
    assert_same_outputs(ref_root, root)
