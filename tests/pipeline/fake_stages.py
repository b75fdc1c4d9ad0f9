"""Tiny in-memory stage modules for runner tests."""
from __future__ import annotations

import types
from dataclasses import dataclass

import pandas as pd

from pipeline import dag

CALLS: list[str] = []


def make(name, inputs, outputs, run, config=None):
    mod = types.ModuleType(f"fake_{name}")
    mod.__file__ = __file__
    mod.INPUTS, mod.OUTPUTS, mod.run = tuple(inputs), tuple(outputs), run

    @dataclass(frozen=True)
    class Config:
        value: int = 1
        """a knob."""

    mod.Config = config or Config
    return dag.stage_from_module(name, mod)


def frames_df(n, value):
    return pd.DataFrame({"window_id": [0] * n, "frame_id": list(range(n)), "center_frame_id": [0] * n,
                         "offset": list(range(n)), "split": ["train"] * n, "is_center": [False] * n,
                         "n_windows": [value] * n})


def first(inputs, cfg, ctx):
    CALLS.append("first")
    (ctx.output_dir("images") / "a.txt").write_text(str(cfg.value))
    return {"windows": frames_df(3, cfg.value)}


def second(inputs, cfg, ctx):
    CALLS.append("second")
    if not (inputs["images"] / "a.txt").is_file():
        raise AssertionError("dir input not committed")
    if cfg.value < 0:
        raise RuntimeError("boom")
    w = inputs["windows"]
    return {"gt_segments": pd.DataFrame({
        "frame_id": w["frame_id"], "instance_id": w["n_windows"] * cfg.value, "class_id": 2, "area_px": 10,
        "near_depth_frac": 1.0, "kept": True, "drop_reason": ""})}
