"""load_labels: the detector PNGs and the filtered detections table -> WindowLabels."""
import numpy as np
import pandas as pd

from pipeline.images import write_png
from rowmap.window_data import load_labels


def _frames(tmp_path, insts: list[np.ndarray | None]) -> pd.DataFrame:
    rows = []
    for fid, inst in enumerate(insts):
        row = {"frame_id": fid, "height": 2, "width": 3, "det_semantic_path": None, "det_instance_path": None}
        if inst is not None:
            sem = np.where(inst > 0, 2, 1).astype(np.uint8)
            write_png(tmp_path / f"s{fid}.png", sem)
            write_png(tmp_path / f"i{fid}.png", inst.astype(np.uint16))
            row.update(det_semantic_path=f"s{fid}.png", det_instance_path=f"i{fid}.png")
        rows.append(row)
    return pd.DataFrame(rows)


def test_segments_carry_their_score_and_dropped_ones_become_void(tmp_path):
    inst0 = np.array([[0, 1, 1], [2, 2, 3]])
    frames = _frames(tmp_path, [inst0, None])
    dets = pd.DataFrame({"frame_id": [0, 0, 0], "segment_id": [1, 2, 3], "score": [0.9, 0.5, 0.8],
                         "kept": [True, False, True]})
    lab = load_labels(frames, dets, tmp_path)
    assert lab.semantic[0].tolist() == [[1, 2, 2], [255, 255, 2]]         # segment 2 dropped: void
    assert lab.instance[0].tolist() == [[0, 1, 1], [0, 0, 3]]
    assert np.allclose(lab.confidence[0], [[1, 0.9, 0.9], [0, 0, 0.8]])
    assert (lab.semantic[1] == 255).all() and (lab.confidence[1] == 0).all()  # no detector output: all void
    assert lab.instance.dtype == np.int16                                    # 2 bytes a pixel, not 4


def test_without_detections_every_segment_scores_one_and_large_ids_fit(tmp_path):
    frames = _frames(tmp_path, [np.array([[0, 40000, 40000], [7, 7, 0]])])
    lab = load_labels(frames, None, tmp_path)
    assert lab.instance[0].tolist() == [[0, 40000, 40000], [7, 7, 0]]      # past int16: held as int32
    assert (lab.confidence == 1).all()


def test_the_largest_int16_id_stays_int16(tmp_path):
    lab = load_labels(_frames(tmp_path, [np.array([[0, 32767, 1], [1, 0, 0]])]), None, tmp_path)
    assert lab.instance.dtype == np.int16 and lab.instance[0, 0, 1] == 32767
