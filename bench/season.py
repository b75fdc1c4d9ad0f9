"""`pag bench season`: synthetic seasons (one row recorded on several days) tracked and scored against ground truth.

    pag bench season [--days 0 7 14 21] [--seeds 0 1] [--set synth.KEY=VALUE ...] [--oracle] [--track-set track.KEY=V]

Each season is the rows `synth_season_s<seed>_d<day>` (synth.seed, synth.day; the --set settings on every row)
through the whole DAG, then `pag track` over them (pipeline/season.py), scored: association precision and
recall over consecutive dates, IDF1, registration error, growth-rate error, harvest/set event F1 and the
tracking time as a share of the rows' pipeline time. `--oracle` replaces the NeRF stages by the ground truth's
fruits as each date's odometry frame would place them (seen through the camera nearest each fruit), with
measurement noise (ORACLE_NOISE): it scores the tracker alone, in seconds per season, on seeds, densities
and growth rates the tracker was not tuned on. Results: data/bench/season[_oracle].parquet (one row per
season and metric).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa

import schemas
from bench._common import write_parquet
from nerf.geometry import pose_matrix
from pipeline import io, season
from pipeline.catalog import dataset
from pipeline.classes import class_name
from pipeline.runner import Runner
from rowmap.structure import structure_of_frames

ORACLE_NOISE = {"position_m": 0.004, "diameter_m": 0.003, "miss_rate": 0.03}
"""Measurement noise of --oracle fruits: centre and diameter standard deviations, and the share of fruits missed."""
ORACLE_MIN_FRAMES = 3
"""--oracle keeps near-row fruits visible in at least this many frames (the rows' counted population)."""


def _fill(df: pd.DataFrame, table: str) -> pd.DataFrame:
    """df with every other column of `table` filled with a neutral value (0, False, '' or null)."""
    out = {}
    for f in schemas.get(table):
        if f.name in df.columns:
            out[f.name] = df[f.name]
        elif f.nullable:
            out[f.name] = pd.Series([None] * len(df), dtype=object)
        elif pa.types.is_boolean(f.type):
            out[f.name] = False
        elif pa.types.is_string(f.type):
            out[f.name] = ""
        else:
            out[f.name] = 0
    return pd.DataFrame(out, index=df.index)


def oracle_row(data_root: Path, seq: str, rng: np.random.Generator, max_depth_m: float) -> None:
    """Write fruits.parquet and panoptic_frames.parquet of an ingested synthetic row from its ground truth:
    each fruit placed in the row's odometry frame through the frame whose true camera x is nearest it, plus
    ORACLE_NOISE; and its structure.parquet (stuff within max_depth_m, the row's fruit_count.max_depth_m) from
    the recorded depth and the detector's labels, placed the same way (a map as the pipeline's refined poses
    give it: consistent within itself, in the odometry's frame)."""
    from rowmap.ground_truth import gt_poses_by_frame

    frames = io.read_table(dataset("frames").path(data_root, seq), "frames")
    gt = data_root / "raw" / seq / "gt"
    by_frame = gt_poses_by_frame(pd.read_parquet(gt / "poses.parquet"), frames)
    cols = ["tx", "ty", "tz", "qx", "qy", "qz", "qw"]
    both = frames[["frame_id", *cols]].merge(by_frame[["frame_id", *cols]], on="frame_id", suffixes=("_odo", "_gt"))
    rel = pose_matrix(both[[f"{c}_odo" for c in cols]].to_numpy()) @ np.linalg.inv(
        pose_matrix(both[[f"{c}_gt" for c in cols]].to_numpy()))
    g = pd.read_parquet(gt / "fruits.parquet")
    g = g[g.near_row & (g.n_frames_visible >= ORACLE_MIN_FRAMES)]
    g = g[rng.random(len(g)) >= ORACLE_NOISE["miss_rate"]].reset_index(drop=True)
    xyz = g[["x_m", "y_m", "z_m"]].to_numpy(np.float64)
    f = np.abs(both.tx_gt.to_numpy()[None] - xyz[:, :1]).argmin(1)
    row = np.einsum("fij,fj->fi", rel[f, :3, :3], xyz) + rel[f, :3, 3] + rng.normal(0, ORACLE_NOISE["position_m"],
                                                                                      xyz.shape)
    fruits = pd.DataFrame({
        "fruit_id": np.arange(1, len(g) + 1, dtype=np.int32), "class_id": g.class_id.astype(np.int32),
        "class_name": [class_name(int(c)) for c in g.class_id], "class_confidence": 1.0,
        "x_m": row[:, 0], "y_m": row[:, 1], "z_m": row[:, 2],
        "diameter_m": g.diameter_m.to_numpy() + rng.normal(0, ORACLE_NOISE["diameter_m"], len(g)),
        "median_depth_m": 0.6, "near_row": True, "counted": True, "n_points": 500, "n_frames": 10, "n_windows": 1,
        "first_frame_id": both.frame_id.to_numpy()[f].astype(np.int32),
        "last_frame_id": both.frame_id.to_numpy()[f].astype(np.int32)})
    pf = frames[["frame_id", *cols]].copy()
    out = dataset("fruits").path(data_root, seq)
    out.parent.mkdir(parents=True, exist_ok=True)
    io.write_table(_fill(fruits, "fruits"), out, "fruits")
    io.write_table(_fill(pf, "panoptic_frames"), dataset("panoptic_frames").path(data_root, seq), "panoptic_frames")
    # the structure as the fruits: true points, each placed through the frame whose true camera x is nearest
    gt_c2w = pose_matrix(frames[["frame_id"]].merge(by_frame, on="frame_id")[cols].to_numpy())
    if len(gt_c2w) != len(frames):
        raise ValueError(f"{seq}: gt/poses.parquet has no pose for {len(frames) - len(gt_c2w)} frames")
    cam_x = both.tx_gt.to_numpy()

    def place(p: np.ndarray) -> np.ndarray:
        k = np.abs(cam_x[None] - p[:, :1]).argmin(1)
        return np.einsum("fij,fj->fi", rel[k, :3, :3], p) + rel[k, :3, 3]

    io.write_table(structure_of_frames(frames, data_root, max_depth_m, gt_c2w, place),
                   dataset("structure").path(data_root, seq), "structure")


def run_season(data_root: Path, seed: int, days: list[int], synth_sets: list[str], track_sets: list[str],
               oracle: bool, name: str) -> dict[str, float]:
    """One season: its rows (synth + ingest with --oracle, else the whole DAG), tracked and scored."""
    seqs = []
    for day in days:
        seq = f"synth_season_s{seed}_d{day:02d}"
        runner = Runner(seq, data_root, overrides=[f"synth.seed={seed}", f"synth.day={day}", *synth_sets],
                        show_progress=False)
        names = [s.name for s in runner.active()]
        runner.run(["synth", "ingest"] if oracle else names)
        if oracle:
            oracle_row(data_root, seq, np.random.default_rng([seed, day, 99]), runner.config["fruit_count"].max_depth_m)
        seqs.append(seq)
    _, scores, _ = season.track(seqs, data_root, track_sets, name=f"_season_{name}_s{seed}")
    return scores


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="pag bench season", description=__doc__.split("\n")[0])
    p.add_argument("--days", type=int, nargs="+", default=[0, 7, 14, 21], help="recording days of the season")
    p.add_argument("--seeds", type=int, nargs="+", default=[0], help="synth seeds: one season each")
    p.add_argument("--set", dest="synth_sets", action="append", default=[], metavar="KEY=VALUE",
                   help="a setting for every row, e.g. synth.fruits_per_m=20 (repeatable)")
    p.add_argument("--track-set", dest="track_sets", action="append", default=[], metavar="track.KEY=VALUE")
    p.add_argument("--oracle", action="store_true", help="ground-truth fruits with noise instead of the NeRF stages")
    p.add_argument("--data-root", type=Path, default=Path("data"))
    p.add_argument("--out", type=Path, default=Path("data/bench"))
    a = p.parse_args(argv)
    name = "season_oracle" if a.oracle else "season"
    rows = []
    for seed in a.seeds:
        scores = run_season(a.data_root, seed, a.days, a.synth_sets, a.track_sets, a.oracle, name)
        rows += [{"seed": seed, "days": " ".join(map(str, a.days)), "settings": " ".join(a.synth_sets),
                  "metric": k, "value": v} for k, v in scores.items()]
        print(f"[bench season] seed {seed}: " + ", ".join(
            f"{k}={scores[k]:.3g}" for k in ("association_precision", "association_recall", "idf1",
                                             "registration_error_median_m", "growth_error_median_mm_per_week",
                                             "harvested_f1", "set_f1", "event_f1", "tracking_cost_share")
            if k in scores))
    df = pd.DataFrame(rows)
    a.out.mkdir(parents=True, exist_ok=True)
    write_parquet(df, a.out / f"{name}.parquet")
    print(f"wrote {a.out / name}.parquet")
    return 0


if __name__ == "__main__":
    sys.exit(main())
