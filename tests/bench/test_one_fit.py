"""Every window fit goes through the one fitting sequence, nerf.fit.fit_panoptic_window: the nerf_fit stage's
task and the benchmarks that fit windows (ablation, compare; pareto through compare) call it with their settings,
and no stage or benchmark imports the sequence's pieces to run a copy of it."""
import ast
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest

import nerf.fit
from bench import ablation, compare
from pipeline.runner import Runner
from stages import nerf_fit

ROOT = Path(__file__).resolve().parents[2]
PIECES = {"nerf.trainer": {"fit_window", "validate"}, "nerf.panoptic.train": {"fit_panoptic"},
          "nerf.panoptic.render": {"render_panoptic"}, "nerf.panoptic.complete": {"complete_instances"},
          "nerf.depth_poses": {"depth_initial_poses"}}
"""The steps of the fitting sequence (module -> names), called in order by nerf/fit.py."""
PIECE_BENCHES = {
    "bench/render.py": "times fit_window's training steps and the renders of one colour fit",
    "bench/skips.py": "times the skips inside the colour and panoptic phases, one phase at a time",
    "bench/step_profile.py": "profiles and times the colour phase's training steps alone, set-up subtracted",
}
"""Benchmarks that time a step of the sequence on its own, not the sequence."""
TINY = ["synth.n_frames=12", "synth.width=64", "synth.height=40", "synth.n_labelled=2", "synth.supersample=1",
        "synth.workers=1", "synth.write_bag=false", "windows.half_width=3"]


class Reached(Exception):
    """Raised by the stand-in for fit_panoptic_window: carries how it was called."""


def pieces_imported(path: Path) -> list[str]:
    out = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module in PIECES:
            out += [f"{node.module}.{a.name}" for a in node.names if a.name in PIECES[node.module]]
    return out


def test_no_stage_or_benchmark_runs_its_own_copy_of_the_fit_sequence():
    files = sorted([*(ROOT / "stages").glob("*.py"), *(ROOT / "bench").glob("*.py")])
    offenders = {p.relative_to(ROOT).as_posix(): pieces_imported(p) for p in files
                 if pieces_imported(p) and p.relative_to(ROOT).as_posix() not in PIECE_BENCHES}
    assert offenders == {}
    assert all(pieces_imported(ROOT / p) for p in PIECE_BENCHES)  # the exemptions are still needed


def test_nerf_fit_task_fits_through_fit_panoptic_window(tmp_path, monkeypatch):
    frames = pd.DataFrame({"frame_id": [10, 11, 12, 13], "labelled": [False, True, False, False],
                           "is_center": [False, False, True, False]})
    cfg = nerf_fit.Config(depth_poses="scale", render_scale=0.5, seed=3)
    payload = nerf_fit.window_payload(2, frames, cfg, nerf_fit.model_config(cfg), "cpu", tmp_path, tmp_path, None)
    window = object()
    monkeypatch.setattr(nerf_fit, "load_window", lambda f, root: window)
    monkeypatch.setattr(nerf_fit, "load_labels", lambda f, dets, root: ("labels of", list(f.frame_id), dets, root))

    def stand_in(*args, **kwargs):
        raise Reached(args, kwargs)

    monkeypatch.setattr(nerf.fit, "fit_panoptic_window", stand_in)
    with pytest.raises(Reached) as got:
        nerf_fit.fit_one(payload)
    (data, labels, mcfg, pcfg), kw = got.value.args
    assert data is window and labels() == ("labels of", [10, 11, 12, 13], None, tmp_path.resolve())
    assert mcfg == replace(nerf_fit.model_config(cfg), seed=5) and pcfg == cfg.panoptic
    assert kw["depth_poses"] == "scale" and kw["render_scale"] == 0.5 and "full_size" not in kw
    assert kw["device"] == "cpu" and kw["name"] == "window 2" and callable(kw["progress"])


@pytest.fixture(scope="module")
def tiny_row(tmp_path_factory):
    root = tmp_path_factory.mktemp("one_fit") / "data"
    Runner("synth_tiny", root, overrides=TINY, show_progress=False).run(["synth", "ingest", "depth_filter", "windows"])
    return root


def recording_stand_in(calls: list):
    """fit_panoptic_window's stand-in: records each call; returns a fit whose renders say 'no fruit'."""
    def fit(data, labels, cfg, pcfg, **kw):
        calls.append(SimpleNamespace(data=data, labels=labels, cfg=cfg, pcfg=pcfg, **kw))
        h, w = data.images.shape[1:3]
        renders = {int(i): {"semantic": np.zeros((h, w), np.uint8), "instance": np.zeros((h, w), np.int32)}
                   for i in np.flatnonzero(~data.is_train)}
        colour = SimpleNamespace(renders=renders, val_psnr={0: 20.0}, params=10, fit_s=1.0, render_s_per_image=0.1,
                                 history=[{"samples_per_ray": 8.0}])
        return SimpleNamespace(colour=colour, panoptic=SimpleNamespace(params=5, fit_s=1.0))
    return fit


def test_ablation_trains_every_variant_through_fit_panoptic_window_on_one_colour_fit(tiny_row, tmp_path,
                                                                                      monkeypatch):
    assert ablation.fit_panoptic_window is nerf.fit.fit_panoptic_window and ablation.fit_colour is nerf.fit.fit_colour
    colours, calls = [], []

    def colour(data, cfg):
        colours.append((data, cfg))
        return "the colour phase"

    monkeypatch.setattr(ablation, "fit_colour", colour)
    monkeypatch.setattr(ablation, "fit_panoptic_window", recording_stand_in(calls))
    df = ablation.run("synth_tiny", 1, colour_steps=5, panoptic_steps=3, threads=1, data_root=tiny_row, out_dir=tmp_path)
    assert len(colours) == 1 and len(calls) == len(ablation.VARIANTS) == len(df)
    data, cfg = colours[0]
    assert cfg.steps == 5 and all(c.data is data and c.cfg is cfg and c.colour == "the colour phase" for c in calls)
    assert all(c.pcfg.steps == 3 for c in calls)
    assert [c.pcfg.grid_mode for c in calls] == [v["grid_mode"] for v in ablation.VARIANTS.values()]
    assert (df.params == 15).all() and (df.val_psnr == 20.0).all()


def test_compare_fits_every_method_through_fit_panoptic_window(tiny_row, tmp_path, monkeypatch):
    assert compare.fit_panoptic_window is nerf.fit.fit_panoptic_window
    calls = []
    monkeypatch.setattr(compare, "fit_panoptic_window", recording_stand_in(calls))
    monkeypatch.setattr(compare, "colmap_window", lambda *a: (None, "no COLMAP in this test"))
    df = compare.run("synth_tiny", [1], colour_steps=5, panoptic_steps=3, val_frames=2, threads=1,
                     data_root=tiny_row, out_dir=tmp_path)
    fitted = [(m, p) for m, p, _, _ in compare.methods(5, False) if p != "COLMAP"]
    assert len(calls) == len(fitted) and (df.status == "skipped").sum() == 1
    assert [c.depth_poses for c in calls] == ["icp" if p == compare.DEPTH_ICP else "off" for _, p in fitted]
    assert all(c.cfg.steps == 5 and c.cfg.seed == 1 and c.pcfg.steps == 3 for c in calls)
    assert all((~c.data.is_train).sum() == 2 for c in calls)
