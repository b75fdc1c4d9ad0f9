"""The detector formats (png_pair, coco_panoptic, coco_instances) ingest to the same detections and label
images; class maps by id and by name; auto recognises each format."""
import json
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import pytest

from pipeline.stage import StageContext
from sources.common import IngestError
from stages import ingest, synth

FORMATS = ("png_pair", "coco_panoptic", "coco_instances")


def make_row(root: Path, fmt: str) -> Path:
    raw = root / "raw" / "t"
    raw.mkdir(parents=True)
    ctx = StageContext(stage="synth", seq="t", data_root=root, staging={"raw": raw}, show_progress=False)
    synth.run({}, synth.Config(n_frames=6, width=48, height=32, n_labelled=1, workers=1, supersample=1, seed=5,
                               write_bag=False, det_false_pos_rate=1.0, detections_format=fmt), ctx)
    return raw


def run_ingest(raw: Path, tmp: Path, **cfg):
    staging = tmp / f"stage_{len(list(tmp.glob('stage_*')))}"
    staging.mkdir()
    ctx = StageContext(stage="ingest", seq="t", data_root=raw.parents[1], staging={"images": staging},
                       show_progress=False)
    out = ingest.run({"raw": raw}, ingest.Config(**cfg), ctx)
    return out, ctx, staging


def label_images(out: dict, raw: Path, staging: Path) -> list[tuple[np.ndarray, np.ndarray]]:
    """(semantic, instance) per frame, read wherever the frames table points (raw/ or images/)."""
    imgs = []
    for fr in out["frames"].itertuples():
        pair = []
        for p in (fr.det_semantic_path, fr.det_instance_path):
            path = raw.parents[1] / p if p.startswith("raw/") else staging / Path(p).relative_to("interim/t/images")
            pair.append(cv2.imread(str(path), cv2.IMREAD_UNCHANGED))
        imgs.append(tuple(pair))
    return imgs


@pytest.fixture(scope="module")
def rows(tmp_path_factory) -> dict[str, Path]:
    return {fmt: make_row(tmp_path_factory.mktemp(fmt), fmt) for fmt in FORMATS}


def test_synth_writes_each_format(rows):
    det = {fmt: sorted(p.name for p in (raw / "pred_seg").iterdir()) for fmt, raw in rows.items()}
    assert det["png_pair"] == ["instance", "scores.csv", "semantic"]
    assert det["coco_panoptic"] == ["panoptic", "panoptic.json"]
    assert det["coco_instances"] == ["images.json", "instances.json", "semantic"]
    ann = json.loads((rows["coco_panoptic"] / "pred_seg" / "panoptic.json").read_text())
    png = cv2.imread(str(rows["coco_panoptic"] / "pred_seg" / "panoptic" / ann["annotations"][0]["file_name"]))
    png = png.astype(np.int64)
    ids = png[:, :, 2] + 256 * png[:, :, 1] + 65536 * png[:, :, 0]
    assert set(np.unique(ids)) - {0} == {s["id"] for s in ann["annotations"][0]["segments_info"]}


def test_all_three_formats_ingest_to_the_same_detections_and_label_images(rows, tmp_path):
    ref = None
    for fmt in FORMATS:
        out, ctx, staging = run_ingest(rows[fmt], tmp_path)
        assert ctx.summary["detections_format"] == fmt
        imgs = label_images(out, rows[fmt], staging)
        if ref is None:
            ref = out, imgs
            assert len(out["detections"]) > 6 and out["detections"]["frame_id"].nunique() == 6
            continue
        pd.testing.assert_frame_equal(out["detections"], ref[0]["detections"])
        cols = [c for c in out["frames"].columns if not c.startswith("det_")]
        pd.testing.assert_frame_equal(out["frames"][cols], ref[0]["frames"][cols])
        for (s, i), (rs, ri) in zip(imgs, ref[1]):
            assert s.dtype == np.uint8 and i.dtype == np.uint16
            assert np.array_equal(s, rs) and np.array_equal(i, ri), fmt


def test_explicit_format_that_is_not_there_is_an_error(rows, tmp_path):
    with pytest.raises(IngestError, match=r"no coco_panoptic JSON in .*pred_seg; the folder has: \['images.json'"):
        run_ingest(rows["coco_instances"], tmp_path, detections_format="coco_panoptic")
    with pytest.raises(IngestError, match=r"png_pair format needs semantic/ and instance/ folders; missing "
                                          r"\['instance'\]"):
        run_ingest(rows["coco_instances"], tmp_path, detections_format="png_pair")
