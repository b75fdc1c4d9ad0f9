"""pag bench pose_prior: reference poses matched by stamp, and the bench's fits on the real office excerpt."""
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from bench import pose_prior, real_rgbd
from pipeline.runner import Runner

ROW = Path(__file__).resolve().parents[1] / "data" / "sun3d_office_12f"


def test_reference_positions_by_stamp_and_missing_ones_named(tmp_path):
    gt = tmp_path / "raw" / "r" / "gt"
    gt.mkdir(parents=True)
    pd.DataFrame({"frame_id": [0, 1, 2], "stamp_ns": [30, 10, 20], "tx": [3.0, 1.0, 2.0], "ty": 0.0, "tz": 0.0,
                  "qx": 0.0, "qy": 0.0, "qz": 0.0, "qw": 1.0}).to_parquet(gt / "poses.parquet")
    frames = pd.DataFrame({"frame_id": [5, 6, 7], "stamp_ns": [10, 20, 30]})   # ingest renumbers frames
    got = pose_prior.reference_positions(tmp_path, "r", frames)
    assert got[:, 0].tolist() == [1.0, 2.0, 3.0]
    with pytest.raises(ValueError, match="no pose at 1 frame stamps"):
        pose_prior.reference_positions(tmp_path, "r", pd.DataFrame({"frame_id": [0, 1], "stamp_ns": [10, 100]}))
    with pytest.raises(FileNotFoundError, match="reference poses"):
        pose_prior.reference_positions(tmp_path, "other", frames)


@pytest.mark.slow  # three short 640x480 fits: `make test-slow`
def test_bench_fits_each_penalty_and_the_unrefined_poses_on_a_real_excerpt(tmp_path):
    seq = real_rgbd.place_row(ROW, tmp_path)
    Runner(seq, data_root=tmp_path, show_progress=False).run(["ingest", "depth_filter", "windows"])
    table = pose_prior.run(seq, tmp_path, penalties=(0.0, 1e4), threads=1,
                           model=dict(steps=60, pose_warmup_steps=10, val_register_every=20))
    assert table.variant.tolist() == ["shift penalty 0", "shift penalty 10000", "no pose refinement"]
    free, held, fixed = (table.iloc[i] for i in range(3))
    assert fixed.shift_train_mm < 1e-3 and fixed.ate_m == pytest.approx(fixed.ate_initial_m, abs=1e-6)
    assert free.shift_train_mm > 0.1                        # refinement moves the cameras
    assert held.shift_train_mm < 0.5 * free.shift_train_mm  # the penalty holds them near their start
    # the office's walls are 1.8-3.6 m away (parallax spread ~0.3/m, below 1/m): the weight grows over the penalty
    assert free.shift_weight == 0 and held.shift_weight > 1e4
    assert np.isfinite(table[["ate_m", "ate_train_m", "ate_val_m", "train_psnr"]].to_numpy()).all()
