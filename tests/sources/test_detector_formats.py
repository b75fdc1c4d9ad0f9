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
        if fr.det_instance_path is None:
            imgs.append((None, None))
            continue
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


# --- hand-written detector files with the detector's own category ids -----------------------------

DET_CATEGORIES = [{"id": 7, "name": "pepper_red"}, {"id": 9, "name": "pepper_green"}, {"id": 20, "name": "leaf"},
                  {"id": 21, "name": "sky"}]


def hand_row(rows, tmp_path) -> tuple[Path, list[int]]:
    """A copy of the synthetic row whose pred_seg/ holds hand-written COCO instance results for frame 1."""
    import shutil
    raw = tmp_path / "data" / "raw" / "t"
    shutil.copytree(rows["coco_instances"], raw)
    shutil.rmtree(raw / "pred_seg")
    (raw / "pred_seg").mkdir()
    stamps = sorted(int(p.stem) for p in (raw / "rgb").iterdir())
    return raw, stamps


def write_results(raw: Path, stamps: list[int], results: list[dict], categories=DET_CATEGORIES) -> None:
    images = [{"id": n + 1, "file_name": f"{s}.jpg", "height": 32, "width": 48} for n, s in enumerate(stamps)]
    (raw / "pred_seg" / "detections.json").write_text(json.dumps(
        {"images": images, "annotations": results, "categories": categories}))


def box(y0, y1, x0, x1):
    from sources import coco
    m = np.zeros((32, 48), bool)
    m[y0:y1, x0:x1] = True
    return coco.encode(m)


def test_instances_overlaps_by_score_polygons_names_and_default_score(rows, tmp_path):
    raw, stamps = hand_row(rows, tmp_path)
    write_results(raw, stamps, [
        {"image_id": 2, "category_id": 7, "segmentation": box(0, 10, 0, 10), "score": 0.4},
        {"image_id": 2, "category_id": 9, "segmentation": box(5, 15, 5, 15), "score": 0.9},
        {"image_id": 2, "category_id": 7, "segmentation": [[30.0, 20.0, 40.0, 20.0, 40.0, 30.0, 30.0, 30.0]]},
        {"image_id": 2, "category_id": 20, "segmentation": box(20, 32, 0, 20), "score": 0.8},
        {"image_id": 3, "category_id": 7, "segmentation": box(0, 4, 0, 4), "score": 0.3},
        {"image_id": 3, "category_id": 9, "segmentation": box(0, 5, 0, 5), "score": 0.6},
    ])
    out, ctx, staging = run_ingest(raw, tmp_path, class_map={"pepper_red": "fruit_red", 9: 2, "leaf": "plant"})
    assert ctx.summary["detections_format"] == "coco_instances"
    det = out["detections"]
    f1 = det[det.frame_id == 1].set_index("segment_id")
    # the 0.9 green box is painted over the 0.4 red one; the polygon gets score 1.0 (counted); the leaf is stuff
    assert f1.class_id.to_dict() == {1: 4, 2: 2, 3: 4} and f1.loc[3, "score"] == 1.0
    assert f1.loc[2, "area_px"] == 100 and f1.loc[1, "area_px"] == 100 - 25 and 80 < f1.loc[3, "area_px"] < 130
    assert ctx.summary["segments_without_score_set_to_1"] == 1
    # frame 2's low-score mask lies wholly under a higher one: dropped and counted
    assert det[det.frame_id == 2].segment_id.tolist() == [2] and ctx.summary["segments_hidden_by_higher_scores"] == 1
    sem, inst = label_images(out, raw, staging)[1]
    assert sem[25, 5] == 1 and inst[25, 5] == 0          # leaf -> plant, stuff
    assert sem[10, 10] == 2 and inst[10, 10] == 2
    assert sem[31, 47] == 255 and inst[31, 47] == 0      # no semantic PNG and no mask: void
    # frames with no result but in the images list are detected with nothing; frames 3.. are still listed
    assert out["frames"]["det_instance_path"].notna().all()


def test_instances_stuff_comes_from_the_semantic_png(rows, tmp_path):
    raw, stamps = hand_row(rows, tmp_path)
    write_results(raw, stamps, [{"image_id": 1, "category_id": 7, "segmentation": box(0, 10, 0, 10), "score": 0.5}])
    (raw / "pred_seg" / "semantic").mkdir()
    sem_in = np.full((32, 48), 21, np.uint8)
    sem_in[:, 24:] = 20
    sem_in[0, 40] = 7  # a fruit pixel of the semantic map that no instance mask covers: void
    cv2.imwrite(str(raw / "pred_seg" / "semantic" / f"{stamps[0]}.png"), sem_in)
    out, ctx, staging = run_ingest(raw, tmp_path, class_map={7: "fruit_red", 20: "plant", 21: "background"})
    sem, inst = label_images(out, raw, staging)[0]
    assert sem[5, 5] == 4 and inst[5, 5] == 1 and sem[20, 5] == 0 and sem[20, 30] == 1 and sem[0, 40] == 255
    assert ctx.summary["semantic_thing_pixels_without_mask_set_to_void"] == 1
    assert ctx.summary["frames_without_semantic_png"] == 5


def test_unmapped_categories_are_an_error_listing_them_or_void(rows, tmp_path):
    raw, stamps = hand_row(rows, tmp_path)
    write_results(raw, stamps, [{"image_id": 1, "category_id": 7, "segmentation": box(0, 10, 0, 10), "score": 0.5},
                                {"image_id": 1, "category_id": 21, "segmentation": box(20, 30, 0, 10), "score": 0.5}])
    with pytest.raises(IngestError, match=r"detector categories \['7 \(pepper_red\)', '21 \(sky\)'\] have no project "
                                          r"class; set ingest.class_map .* Classes: 0=background, 1=plant"):
        run_ingest(raw, tmp_path)
    with pytest.raises(IngestError, match=r"categories \['21 \(sky\)'\] have no project class; add them to "
                                          r".*class_map.yaml"):
        (raw / "class_map.yaml").write_text("pepper_red: fruit_red\n")
        run_ingest(raw, tmp_path, class_map="class_map.yaml")
    out, ctx, staging = run_ingest(raw, tmp_path, class_map="class_map.yaml", unmapped="void")
    assert ctx.summary["unmapped_categories_set_to_void"] == 1 and len(out["detections"]) == 1
    assert label_images(out, raw, staging)[0][0][25, 5] == 255


def test_class_map_errors_name_what_is_wrong(rows, tmp_path):
    raw, stamps = hand_row(rows, tmp_path)
    write_results(raw, stamps, [{"image_id": 1, "category_id": 7, "segmentation": box(0, 10, 0, 10), "score": 0.5}])
    with pytest.raises(IngestError, match=r"entry 7: 'tomato' is not a project class; classes: 0=background"):
        run_ingest(raw, tmp_path, class_map={7: "tomato"})
    with pytest.raises(IngestError, match=r"category name\(s\) \['peper_red'\] are not among the detector's "
                                          r"categories .*\['leaf', 'pepper_green', 'pepper_red', 'sky'\]"):
        run_ingest(raw, tmp_path, class_map={"peper_red": "fruit_red"})
    with pytest.raises(IngestError, match="class_map: file .*nope.yaml does not exist"):
        run_ingest(raw, tmp_path, class_map="nope.yaml")
    write_results(raw, stamps, [{"image_id": 1, "category_id": 7, "segmentation": box(0, 10, 0, 10)}], categories=[])
    with pytest.raises(IngestError, match=r"maps category names \['pepper_red'\] but .*detections.json lists no "
                                          r"categories"):
        run_ingest(raw, tmp_path, class_map={"pepper_red": "fruit_red"})


def test_class_map_from_the_command_line(tmp_path):
    from pipeline import config as cfgmod
    cfg = cfgmod.resolve({"ingest": ingest.Config}, cfgmod.parse_set(["ingest.class_map={7: fruit_red, leaf: plant}",
                                                                     "ingest.unmapped=void"]))
    assert cfg["ingest"].class_map == {7: "fruit_red", "leaf": "plant"} and cfg["ingest"].unmapped == "void"
    cfg = cfgmod.resolve({"ingest": ingest.Config}, cfgmod.parse_set(["ingest.class_map=maps/det.yaml"]))
    assert cfg["ingest"].class_map == "maps/det.yaml"


def test_panoptic_with_detector_ids_large_segment_ids_and_missing_scores(rows, tmp_path):
    raw, stamps = hand_row(rows, tmp_path)
    ids = np.zeros((32, 48), np.int64)
    ids[:, :] = 5_000_000          # stuff: leaf
    ids[2:8, 2:8] = 70_001         # thing ids beyond 16 bits: renumbered 1..n in segments_info order
    ids[10:20, 10:20] = 70_002
    ids[30:, :] = 0                # unlabelled
    (raw / "pred_seg" / "panoptic").mkdir()
    rgb = np.stack([ids % 256, ids // 256 % 256, ids // 65536], -1).astype(np.uint8)
    cv2.imwrite(str(raw / "pred_seg" / "panoptic" / f"{stamps[0]}.png"), rgb[:, :, ::-1])
    (raw / "pred_seg" / "panoptic.json").write_text(json.dumps({"annotations": [{
        "image_id": 1, "file_name": f"{stamps[0]}.png", "segments_info": [
            {"id": 70_002, "category_id": 7, "isthing": 1, "score": 0.8},
            {"id": 70_001, "category_id": 9, "isthing": 1},
            {"id": 5_000_000, "category_id": 20, "isthing": 0}]}], "categories": DET_CATEGORIES}))
    out, ctx, staging = run_ingest(raw, tmp_path, class_map={7: "fruit_red", 9: "fruit_green", 20: "plant"})
    assert ctx.summary["detections_format"] == "coco_panoptic"
    det = out["detections"].set_index("segment_id")
    assert det.class_id.to_dict() == {1: 4, 2: 2} and det.score.to_dict() == {1: 0.8, 2: 1.0}
    assert det.area_px.to_dict() == {1: 100, 2: 36}
    assert ctx.summary["segments_without_score_set_to_1"] == 1 and ctx.summary["panoptic_segment_ids_renumbered"] == 2
    sem, inst = label_images(out, raw, staging)[0]
    assert inst[15, 15] == 1 and inst[5, 5] == 2 and sem[25, 30] == 1 and inst[25, 30] == 0 and sem[31, 0] == 255
    assert out["frames"]["det_instance_path"].notna().sum() == 1 and ctx.summary["frames_without_detections"] == 5


def test_instances_semantic_png_with_fruit_under_the_masks_voids_nothing(rows, tmp_path):
    # the synthetic semantic PNGs paint every detected fruit; the masks cover all of it, so nothing is voided
    _, ctx, _ = run_ingest(rows["coco_instances"], tmp_path)
    assert "semantic_thing_pixels_without_mask_set_to_void" not in ctx.summary


def test_png_pair_with_the_detector_own_ids_and_a_class_map(rows, tmp_path):
    import shutil
    ref, _, ref_dir = run_ingest(rows["png_pair"], tmp_path)
    raw = tmp_path / "data" / "raw" / "t"
    shutil.copytree(rows["png_pair"], raw)
    for p in (raw / "pred_seg" / "semantic").iterdir():     # detector ids = project id + 10
        sem = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        cv2.imwrite(str(p), np.where(sem == 255, 255, sem + 10).astype(np.uint8))
    scores = pd.read_csv(raw / "pred_seg" / "scores.csv")
    scores.assign(class_id=scores.class_id + 10).to_csv(raw / "pred_seg" / "scores.csv", index=False)
    with pytest.raises(IngestError, match=r"semantic PNG .* holds class ids \[10, 11"):
        run_ingest(raw, tmp_path)
    out, ctx, staging = run_ingest(raw, tmp_path, class_map={10: 0, 11: 1, 12: 2, 13: 3, 14: 4})
    pd.testing.assert_frame_equal(out["detections"], ref["detections"])
    for (s, i), (rs, ri) in zip(label_images(out, raw, staging), label_images(ref, rows["png_pair"], ref_dir)):
        assert np.array_equal(s, rs) and np.array_equal(i, ri)
    # green fruit mapped to plant: its segments leave the table and the instance PNGs
    out, ctx, staging = run_ingest(raw, tmp_path, class_map={10: 0, 11: 1, 12: "plant", 13: 3, 14: 4})
    assert 2 not in set(out["detections"].class_id) and len(out["detections"]) == (ref["detections"].class_id != 2).sum()
    for (s, i), (rs, ri) in zip(label_images(out, raw, staging), label_images(ref, rows["png_pair"], ref_dir)):
        green = np.isin(ri, ref["detections"].query("class_id == 2").segment_id) & (rs == 2)
        assert (s[green] == 1).all() and (i[green] == 0).all()
