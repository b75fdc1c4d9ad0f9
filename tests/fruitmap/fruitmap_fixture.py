"""A tiny synthetic row run up to `windows`, plus nerf_fit outputs fabricated from its ground truth.

The NeRF stage is slow and its panoptic renders are not what these tests are about, so `fabricate_nerf`
writes what nerf_fit's contract promises (data/README.md), built from the exact ground truth: per window,
every validation frame's rgb / depth (mm) / semantic / instance PNGs listed in renders.parquet, with
instance ids permuted per window (window-local slots), window_poses = the true camera poses, window_metrics
all 'ok'.
"""
from __future__ import annotations

import shutil
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa

import schemas
from pipeline import io
from pipeline.images import read_label
from rowmap import renders
from pipeline.runner import Runner

SEQ = "synth_fm"
TINY = ["synth.n_frames=16", "synth.width=128", "synth.height=72", "synth.n_labelled=3", "synth.supersample=1",
        "synth.workers=1", "synth.write_bag=false", "synth.seed=4", "windows.half_width=5",
        "windows.val_every=2"]     # 16 frames: every other one fused, so each fruit is in several fused frames
POSE_COLS = ["tx", "ty", "tz", "qx", "qy", "qz", "qw"]


class Row:
    """Paths and tables of one prepared tiny row."""

    def __init__(self, root: Path):
        self.root = root
        self.interim = root / "interim" / SEQ
        self.processed = root / "processed" / SEQ
        self.raw = root / "raw" / SEQ
        self.frames = pd.read_parquet(self.interim / "frames.parquet")
        self.windows = pd.read_parquet(self.interim / "windows.parquet")
        self.gt_fruits = pd.read_parquet(self.raw / "gt" / "fruits.parquet")
        self.gt_poses = pd.read_parquet(self.raw / "gt" / "poses.parquet")
        self.gt_segments = pd.read_parquet(self.interim / "gt_segments.parquet")

    def runner(self, *extra: str) -> Runner:
        return Runner(SEQ, data_root=self.root, overrides=[*TINY, *extra], show_progress=False)


SlotHook = Callable[[int, int, np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]
"""(window_id, frame_id, semantic, slots) -> (semantic, slots): a perturbation of one rendered frame."""


def fabricate_nerf(row: Row, seed: int = 0, hook: SlotHook | None = None) -> None:
    """Write window_poses, window_metrics, renders and the render files from the ground truth."""
    rng = np.random.default_rng(seed)
    nerf = row.processed / "nerf"
    shutil.rmtree(nerf, ignore_errors=True)
    frames = row.frames.set_index("frame_id")
    gt = row.gt_poses.set_index("frame_id")
    max_id = int(row.gt_fruits.fruit_id.max())
    pose_rows, metric_rows, render_rows = [], [], []
    for wid, w in row.windows.groupby("window_id"):
        perm = np.r_[0, rng.permutation(max_id) + 1 + 7 * int(wid)]      # window-local slots, 0 stays stuff
        (nerf / renders.file_name(wid, "rgb", 0)).parent.mkdir(parents=True)
        for r in w.itertuples(index=False):
            fr = frames.loc[r.frame_id]
            odo = fr[POSE_COLS].to_numpy(np.float64)
            true = gt.loc[r.frame_id, POSE_COLS].to_numpy(np.float64)
            pose_rows.append({"window_id": wid, "frame_id": r.frame_id, "split": r.split, "source": "odometry",
                              "refined": True, **dict(zip(POSE_COLS, true)),
                              "delta_t_m": float(np.linalg.norm(true[:3] - odo[:3])), "delta_rot_deg": 0.0})
            if r.split != "val":
                continue
            sem = read_label(row.root / fr.gt_semantic_path, "gt").astype(np.uint8)
            inst = read_label(row.root / fr.gt_instance_path, "gt")
            slots = perm[inst]
            if hook is not None:
                sem, slots = hook(int(wid), int(r.frame_id), sem, slots)
            # the input rgb and depth PNGs are stored as renders are (8-bit colour, 16-bit mm): copied as they are
            for kind, src in (("rgb", fr.rgb_path), ("depth", fr.depth_path)):
                shutil.copy(row.root / src, nerf / renders.file_name(wid, kind, r.frame_id))
            renders.write_frame(nerf, wid, r.frame_id, {"semantic": sem, "instance": slots,
                                                        "fruit": (slots > 0).astype(np.float32)})
            render_rows += [(wid, r.frame_id, kind) for kind in renders.KINDS]
        metric_rows.append({"window_id": wid, "center_frame_id": int(w.center_frame_id.iloc[0]), "status": "ok",
                            "error": "", "preset": "cpu", "device": "cpu", "threads": 1,
                            "n_train": int((w.split == "train").sum()), "n_val": int((w.split == "val").sum()),
                            "params": 1000, "steps": 10, "fit_s": 1.5 + wid, "render_s_per_image": 0.1,
                            "samples_per_ray": 8.0, "val_psnr": 25.0 + wid, "train_psnr": 26.0,
                            "checkpoint_path": f"processed/{SEQ}/nerf/window_{wid:03d}/checkpoint.pt"})
    io.write_table(complete(pd.DataFrame(pose_rows), "window_poses"), row.processed / "window_poses.parquet",
                   "window_poses")
    io.write_table(complete(pd.DataFrame(metric_rows), "window_metrics"), row.processed / "window_metrics.parquet",
                   "window_metrics")
    rel = nerf.relative_to(row.root)
    table = pd.DataFrame([(w, f, k, (rel / renders.file_name(w, k, f)).as_posix()) for w, f, k in render_rows],
                         columns=["window_id", "frame_id", "kind", "path"])
    io.write_table(table, row.processed / "renders.parquet", "renders")


def complete(df: pd.DataFrame, table: str) -> pd.DataFrame:
    """Columns the schema has beyond those this fixture knows (nerf_fit's tables grow): 0 or ''."""
    for f in schemas.get(table):
        if f.name not in df.columns:
            df[f.name] = "" if pa.types.is_string(f.type) else (False if pa.types.is_boolean(f.type) else 0)
    return df


def copy_row(upstream: Path, dest: Path, seed: int = 0, hook: SlotHook | None = None) -> Row:
    """A fresh copy of the upstream row under `dest` with fabricated NeRF outputs."""
    shutil.copytree(upstream, dest, symlinks=True)
    row = Row(dest)
    fabricate_nerf(row, seed, hook)
    return row


def run_stages(row: Row, *extra: str) -> None:
    row.runner(*extra).run(list(FRUITMAP_STAGES), force=True)


FRUITMAP_STAGES = ("panoptic_fusion", "fruit_count", "evaluate", "report")


