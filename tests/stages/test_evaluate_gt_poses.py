"""Ground-truth poses are matched to the ingested frames by stamp, so a frame skipped at ingest shifts nothing."""
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

import schemas
from nerf.metrics import ate_rmse
from pipeline.stage import StageContext
from stages import evaluate, ingest, synth

POSE = ["tx", "ty", "tz", "qx", "qy", "qz", "qw"]


@pytest.fixture
def row(tmp_path) -> Path:
    """A tiny synthetic row without gt/fruits.parquet (poses are what is scored here)."""
    raw = tmp_path / "raw" / "t"
    raw.mkdir(parents=True)
    ctx = StageContext(stage="synth", seq="t", data_root=tmp_path, staging={"raw": raw}, show_progress=False)
    synth.run({}, synth.Config(n_frames=8, width=48, height=32, n_labelled=2, workers=1, supersample=1, seed=5), ctx)
    (raw / "gt" / "fruits.parquet").unlink()
    return raw


def ingest_frames(raw: Path) -> pd.DataFrame:
    staging = raw.parents[1] / "images"
    staging.mkdir()
    ctx = StageContext(stage="ingest", seq="t", data_root=raw.parents[1], staging={"images": staging},
                       show_progress=False)
    return ingest.run({"raw": raw}, ingest.Config(), ctx)["frames"]


def evaluate_with_odometry_poses(raw: Path, frames: pd.DataFrame) -> tuple[pd.Series, StageContext]:
    """evaluate on one window holding every frame, its refined poses equal to the odometry."""
    ids = frames.frame_id.astype(np.int32)
    windows = pd.DataFrame({"window_id": np.int32(0), "frame_id": ids, "center_frame_id": np.int32(0),
                            "offset": ids, "split": "train", "is_center": False, "n_windows": np.int32(1)})
    poses = frames[["frame_id", *POSE]].assign(window_id=np.int32(0), split="train", source="odometry",
                                               refined=True, delta_t_m=0.0, delta_rot_deg=0.0)
    metrics = pd.DataFrame({"window_id": [0], "status": ["ok"], "val_psnr": [20.0]})
    inputs = {"raw": raw, "frames": frames, "windows": windows, "window_poses": poses, "window_metrics": metrics,
              "renders": schemas.empty("renders"), "gt_segments": schemas.empty("gt_segments"),
              "panoptic_frames": schemas.empty("panoptic_frames"), "fruits": schemas.empty("fruits"),
              "counts": schemas.empty("counts")}
    ctx = StageContext(stage="evaluate", seq="t", data_root=raw.parents[1], show_progress=False)
    out = evaluate.run(inputs, evaluate.Config(), ctx)["evaluation"]
    return out[out.scope == "window_000"].set_index("metric").value, ctx


def test_bad_input_gt_poses_of_a_row_with_a_frame_skipped_at_ingest_give_the_true_ate(row):
    stamps = sorted(int(p.stem) for p in (row / "rgb").glob("*.png"))
    (row / "depth" / f"{stamps[3]}.png").unlink()   # the fourth frame is skipped: ingest renumbers the rest
    gt = pd.read_parquet(row / "gt" / "poses.parquet")
    gt = gt[gt.stamp_ns != stamps[6]]   # and one frame has no true pose
    gt.to_parquet(row / "gt" / "poses.parquet")
    frames = ingest_frames(row)
    assert len(frames) == 7 and stamps[3] not in frames.stamp_ns.tolist()
    scores, ctx = evaluate_with_odometry_poses(row, frames)
    both = frames.merge(gt, on="stamp_ns", suffixes=("", "_gt"))   # what each frame's true pose is
    true_ate = ate_rmse(both[["tx", "ty", "tz"]].to_numpy(), both[["tx_gt", "ty_gt", "tz_gt"]].to_numpy())
    assert scores["ate_odometry_m"] == pytest.approx(true_ate, rel=1e-9, abs=1e-12)
    assert scores["ate_refined_m"] == pytest.approx(true_ate, rel=1e-9, abs=1e-12)
    assert len(both) == 6 and ctx.summary["frames_without_gt_pose"] == 1
    # matched by frame_id instead, every frame after the skipped one would take its successor's true pose
    shifted = frames.merge(gt, on="frame_id", suffixes=("", "_gt"))
    wrong = ate_rmse(shifted[["tx", "ty", "tz"]].to_numpy(), shifted[["tx_gt", "ty_gt", "tz_gt"]].to_numpy())
    assert abs(wrong - true_ate) > 1e-3


def test_gt_poses_match_the_nearest_stamp_within_half_a_frame_period():
    frames = pd.DataFrame({"frame_id": [0, 1, 2, 3], "stamp_ns": [0, 100, 200, 400]})
    gt = pd.DataFrame({"frame_id": [7, 8, 9, 10], "stamp_ns": [2, 96, 260, 399], "tx": [0.0, 1.0, 2.0, 4.0],
                       "ty": 0.0, "tz": 0.0})
    out = evaluate.gt_poses_by_frame(gt, frames)   # tolerance: half the median period, 50 ns
    assert out.frame_id.tolist() == [0, 1, 3] and out.tx.tolist() == [0.0, 1.0, 4.0]
    assert list(out.columns) == ["frame_id", "tx", "ty", "tz"]


def test_gt_poses_without_stamps_are_an_error_listing_the_columns(row):
    gt = pd.read_parquet(row / "gt" / "poses.parquet")
    gt.drop(columns=["stamp_ns"]).to_parquet(row / "gt" / "poses.parquet")
    frames = ingest_frames(row)
    with pytest.raises(ValueError, match=r"poses.parquet lacks columns \['stamp_ns'\]; columns: \['frame_id'"):
        evaluate_with_odometry_poses(row, frames)
