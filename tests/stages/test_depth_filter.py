import numpy as np
import pandas as pd
import pytest

from pipeline.images import write_png
from pipeline.stage import StageContext
from stages import depth_filter


def frame_row(fid, **paths):
    row = dict(frame_id=fid, stamp_ns=fid, depth_stamp_ns=fid, width=8, height=4, fx=5.0, fy=5.0, cx=4.0, cy=2.0,
               tx=0.0, ty=0.0, tz=0.0, qx=0.0, qy=0.0, qz=0.0, qw=1.0, rgb_path="x.png", depth_path="d.png",
               depth_scale_m=0.001, valid_depth_frac=1.0, labelled=False, det_semantic_path=None,
               det_instance_path=None, gt_semantic_path=None, gt_instance_path=None)
    row.update(paths)
    return row


@pytest.fixture()
def scene(tmp_path):
    # depth: columns 0-3 at 1.0 m, 4-7 at 2.0 m, one invalid (0) pixel in column 0.
    depth = np.full((4, 8), 1000, np.uint16)
    depth[:, 4:] = 2000
    depth[0, 0] = 0
    inst = np.zeros((4, 8), np.uint16)
    inst[:, 0:2] = 1          # near: 7 of 8 pixels valid and near
    inst[:, 5:8] = 2          # far
    inst[:, 3:5] = 3          # half near, half far -> kept at exactly 50 %
    sem = np.where(inst > 0, 2, 1).astype(np.uint8)
    write_png(tmp_path / "d.png", depth)
    write_png(tmp_path / "i.png", inst)
    write_png(tmp_path / "s.png", sem)
    frames = pd.DataFrame([frame_row(0, det_instance_path="i.png", det_semantic_path="s.png",
                                     gt_instance_path="i.png", gt_semantic_path="s.png")])
    dets = pd.DataFrame({"frame_id": [0, 0, 0, 0], "segment_id": [1, 2, 3, 9], "class_id": [2, 2, 3, 4],
                         "score": [0.9, 0.8, 0.7, 0.6], "area_px": [8, 12, 8, 0],
                         "near_depth_frac": np.nan, "kept": True, "drop_reason": ""})
    ctx = StageContext(stage="depth_filter", seq="t", data_root=tmp_path, show_progress=False)
    return frames, dets, ctx


def test_masks_mostly_beyond_max_depth_are_dropped_with_reason(scene):
    frames, dets, ctx = scene
    out = depth_filter.run({"frames": frames, "detections": dets}, depth_filter.Config(), ctx)
    d = out["detections_filtered"].set_index("segment_id")
    assert d.loc[1, "kept"] and d.loc[1, "near_depth_frac"] == pytest.approx(7 / 8)
    assert not d.loc[2, "kept"] and "0% of pixels within 1.5 m" in d.loc[2, "drop_reason"]
    assert d.loc[3, "kept"] and d.loc[3, "near_depth_frac"] == pytest.approx(0.5)
    assert not d.loc[9, "kept"] and d.loc[9, "drop_reason"].startswith("empty mask")
    assert ctx.summary["dropped"] == 2


def test_ground_truth_is_filtered_the_same_way(scene):
    frames, dets, ctx = scene
    out = depth_filter.run({"frames": frames, "detections": dets}, depth_filter.Config(max_depth_m=2.5), ctx)
    gt = out["gt_segments"].set_index("instance_id")
    assert sorted(gt.index) == [1, 2, 3] and gt["kept"].all()
    assert gt.loc[3, "class_id"] == 2 and gt.loc[2, "area_px"] == 12


def test_invalid_config_is_rejected():
    with pytest.raises(ValueError, match="max_depth_m must be > 0"):
        depth_filter.Config(max_depth_m=0)
