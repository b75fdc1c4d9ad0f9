"""Bad input to ingest: each case is a clear error naming the file and what is wrong, or a counted skip
named in the stage summary. README.md (section Bad input) lists every case with its test (`pytest -k bad_input`)."""
import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import pytest
import yaml

from raw_helpers import copy_raw
from pipeline.stage import StageContext
from sources.common import IngestError
from stages import ingest, windows


def run_ingest(raw: Path, tmp: Path, **cfg):
    staging = tmp / f"stage_{len(list(tmp.glob('stage_*')))}"
    staging.mkdir()
    ctx = StageContext(stage="ingest", seq="t", data_root=raw.parents[1], staging={"images": staging},
                       show_progress=False)
    out = ingest.run({"raw": raw}, ingest.Config(**cfg), ctx)
    return out, ctx


@pytest.fixture
def raw(tiny_raw, tmp_path) -> Path:
    return copy_raw(tiny_raw, tmp_path)


def stamps_of(raw: Path) -> list[int]:
    return sorted(int(p.stem) for p in (raw / "rgb").iterdir())


# --- detector output -------------------------------------------------------------------------------

@pytest.mark.parametrize("kind, other", [("instance", "semantic"), ("semantic", "instance")])
def test_bad_input_missing_detector_png_is_a_counted_skip(raw, tmp_path, kind, other):
    st = stamps_of(raw)[2]
    (raw / "pred_seg" / kind / f"{st}.png").unlink()
    out, ctx = run_ingest(raw, tmp_path)
    f = out["frames"].set_index("stamp_ns")
    assert f.loc[st, "det_instance_path"] is None and f["det_instance_path"].notna().sum() == 7
    assert ctx.summary["frames_with_one_detector_png_missing"] == 1 and ctx.summary["frames_without_detections"] == 1
    assert f"pred_seg/{kind}/{st}.png is missing (the {other} PNG is there)" in " ".join(ctx.summary["notes"])
    assert st not in set(out["frames"].stamp_ns[out["detections"].frame_id])


def test_bad_input_corrupt_detector_png_is_a_counted_skip_or_an_error(raw, tmp_path):
    victim = raw / "pred_seg" / "instance" / f"{stamps_of(raw)[4]}.png"
    victim.write_bytes(b"\x89PNG\r\n\x1a\nnot really")
    out, ctx = run_ingest(raw, tmp_path)
    assert ctx.summary["frames_with_unreadable_detector_png"] == 1 and out["frames"]["det_instance_path"].isna().sum() == 1
    assert victim.name in " ".join(ctx.summary["notes"])
    with pytest.raises(IngestError, match=f"detector instance PNG .*{victim.name} is not a readable PNG"):
        run_ingest(raw, tmp_path, on_bad_image="error")


def test_bad_input_detector_png_of_another_size_is_an_error(raw, tmp_path):
    victim = raw / "pred_seg" / "semantic" / f"{stamps_of(raw)[1]}.png"
    cv2.imwrite(str(victim), np.zeros((10, 10), np.uint8))
    with pytest.raises(IngestError, match=rf"{victim.name} are 48x32 / 10x10; the frame is 48x32"):
        run_ingest(raw, tmp_path)


def test_bad_input_detector_semantic_with_unknown_class_is_an_error(raw, tmp_path):
    victim = raw / "pred_seg" / "semantic" / f"{stamps_of(raw)[1]}.png"
    sem = cv2.imread(str(victim), cv2.IMREAD_UNCHANGED)
    sem[0, 0] = 17
    cv2.imwrite(str(victim), sem)
    with pytest.raises(IngestError, match=rf"{victim.name} holds class ids \[17\] that the class table lacks"):
        run_ingest(raw, tmp_path)


def test_bad_input_scores_row_for_a_segment_that_does_not_exist_is_a_counted_skip(raw, tmp_path):
    ref, _ = run_ingest(raw, tmp_path)
    scores = pd.read_csv(raw / "pred_seg" / "scores.csv")
    scores.loc[len(scores)] = [stamps_of(raw)[3], 999, 2, 0.9]
    scores.to_csv(raw / "pred_seg" / "scores.csv", index=False)
    out, ctx = run_ingest(raw, tmp_path)
    assert ctx.summary["scores_rows_for_missing_segments"] == 1
    pd.testing.assert_frame_equal(out["detections"], ref["detections"])


def test_bad_input_scores_row_for_no_frame_and_duplicate_rows_are_counted(raw, tmp_path):
    ref, _ = run_ingest(raw, tmp_path)
    scores = pd.read_csv(raw / "pred_seg" / "scores.csv")
    extra = pd.DataFrame([[stamps_of(raw)[-1] + 10**9, 1, 2, 0.9]], columns=scores.columns)
    pd.concat([scores, scores.iloc[:1], extra]).to_csv(raw / "pred_seg" / "scores.csv", index=False)
    out, ctx = run_ingest(raw, tmp_path)
    assert ctx.summary["scores_rows_without_frame"] == 1 and ctx.summary["scores_rows_duplicate"] == 1
    pd.testing.assert_frame_equal(out["detections"], ref["detections"])


def test_bad_input_scores_csv_with_a_non_integer_id_is_an_error(raw, tmp_path):
    path = raw / "pred_seg" / "scores.csv"
    lines = path.read_text().splitlines()
    lines[3] = lines[3].split(",", 1)[0] + ",seven,2,0.5"
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(IngestError, match=r"scores.csv, data row 3: segment_id = 'seven' is not an integer"):
        run_ingest(raw, tmp_path)


def test_bad_input_no_detector_output_at_all_is_counted(raw, tmp_path):
    shutil.rmtree(raw / "pred_seg")
    out, ctx = run_ingest(raw, tmp_path)
    assert ctx.summary["detections_format"] == "none" and ctx.summary["frames_without_detections"] == 8
    assert out["detections"].empty and ctx.summary["segments"] == 0


EMPTY = {"size": [32, 48], "counts": "P`1"}  # an all-zero 32x48 mask


def coco_row(raw: Path) -> list[int]:
    shutil.rmtree(raw / "pred_seg")
    (raw / "pred_seg").mkdir()
    return stamps_of(raw)


def test_bad_input_coco_result_for_an_image_id_not_in_the_images_list_is_an_error(raw, tmp_path):
    st = coco_row(raw)
    (raw / "pred_seg" / "results.json").write_text(json.dumps(
        {"images": [{"id": 1, "file_name": f"rgb/{st[0]}.png"}],
         "annotations": [{"image_id": 5, "category_id": 2, "segmentation": EMPTY}]}))
    with pytest.raises(IngestError, match=r"results.json: result \[0\] has image_id 5, which is not in the images "
                                          r"list of .*results.json \(1 images\)"):
        run_ingest(raw, tmp_path)


def test_bad_input_coco_image_id_that_is_no_stamp_without_an_images_list_is_an_error(raw, tmp_path):
    coco_row(raw)
    (raw / "pred_seg" / "results.json").write_text(json.dumps(
        [{"image_id": "img_3", "category_id": 2, "segmentation": EMPTY}]))
    with pytest.raises(IngestError, match=r"image_id 'img_3', and there is no images list .* images.json"):
        run_ingest(raw, tmp_path)


def test_bad_input_coco_mask_of_another_size_or_malformed_is_an_error(raw, tmp_path):
    st = coco_row(raw)
    (raw / "pred_seg" / "results.json").write_text(json.dumps(
        [{"image_id": st[1], "category_id": 2, "segmentation": {"size": [30, 48], "counts": "0"}, "score": 1}]))
    with pytest.raises(IngestError, match=r"results.json: result \[0\] \(image_id \d+\): RLE mask is 30x48 .* the "
                                          r"image is 32x48"):
        run_ingest(raw, tmp_path)


def test_bad_input_detections_json_that_is_not_json_is_an_error(raw, tmp_path):
    coco_row(raw)
    (raw / "pred_seg" / "results.json").write_text('[{"image_id": 1,')
    with pytest.raises(IngestError, match=r"results.json is not valid JSON"):
        run_ingest(raw, tmp_path)


def test_bad_input_several_detections_jsons_is_an_error_naming_them(raw, tmp_path):
    st = coco_row(raw)
    for name in ("a.json", "b.json"):
        (raw / "pred_seg" / name).write_text(json.dumps(
            [{"image_id": st[0], "category_id": 2, "segmentation": EMPTY}]))
    with pytest.raises(IngestError, match=r"several detections JSON files \['a.json', 'b.json'\]; choose one with "
                                          r"--set ingest.detections_json=NAME"):
        run_ingest(raw, tmp_path)
    out, ctx = run_ingest(raw, tmp_path, detections_json="b.json")
    assert ctx.summary["detections_format"] == "coco_instances"


def test_bad_input_missing_panoptic_png_is_a_counted_skip(raw, tmp_path):
    st = coco_row(raw)
    (raw / "pred_seg" / "panoptic").mkdir()
    ids = np.zeros((32, 48, 3), np.uint8)
    ids[5:10, 5:10, 2] = 3  # BGR on disk: id 3 in the R channel
    cv2.imwrite(str(raw / "pred_seg" / "panoptic" / f"{st[0]}.png"), ids)
    anns = [{"image_id": i, "file_name": f"{s}.png", "segments_info": [{"id": 3, "category_id": 4, "isthing": 1}]}
            for i, s in enumerate(st[:2])]
    (raw / "pred_seg" / "panoptic.json").write_text(json.dumps({"annotations": anns}))
    out, ctx = run_ingest(raw, tmp_path)
    assert ctx.summary["frames_with_unreadable_detector_png"] == 1 and f"{st[1]}.png is missing" in \
        " ".join(ctx.summary["notes"])
    assert out["detections"][["frame_id", "segment_id", "class_id", "area_px"]].values.tolist() == [[0, 3, 4, 25]]


# --- frames, stamps and odometry -------------------------------------------------------------------

def test_bad_input_duplicate_frame_with_the_same_stamp_under_two_names(raw, tmp_path):
    st = stamps_of(raw)[3]
    shutil.copy(raw / "rgb" / f"{st}.png", raw / "rgb" / f"{st // 10**9}.{st % 10**9:09d}.png")
    out, ctx = run_ingest(raw, tmp_path)
    assert len(out["frames"]) == 8 and ctx.summary["color_duplicate_stamps"] == 1


def test_bad_input_duplicate_frame_1ns_after_another_is_skipped(raw, tmp_path):
    st = stamps_of(raw)[3]
    shutil.copy(raw / "rgb" / f"{st}.png", raw / "rgb" / f"{st + 1}.png")
    out, ctx = run_ingest(raw, tmp_path)
    assert len(out["frames"]) == 8 and st + 1 not in out["frames"]["stamp_ns"].tolist()
    assert ctx.summary["skipped_duplicate_frame"] == 1 and out["frames"]["depth_stamp_ns"].is_unique


def test_bad_input_two_frames_nearest_to_one_depth_image_pair_it_once(raw, tmp_path):
    st = stamps_of(raw)[3]
    shutil.copy(raw / "rgb" / f"{st}.png", raw / "rgb" / f"{st + 30_000_000}.png")
    out, ctx = run_ingest(raw, tmp_path, pair_tolerance_ms=40)
    assert len(out["frames"]) == 8 and out["frames"]["depth_stamp_ns"].is_unique
    assert ctx.summary["skipped_depth_paired_with_another_frame"] == 1


def drop_odometry(raw: Path, lo_ns: int, hi_ns: int) -> None:
    odo = pd.read_csv(raw / "odometry.csv")
    odo[(odo.timestamp <= lo_ns) | (odo.timestamp >= hi_ns)].to_csv(raw / "odometry.csv", index=False)


def test_bad_input_odometry_gap_in_the_middle_of_the_row_skips_and_counts(raw, tmp_path):
    st = stamps_of(raw)
    drop_odometry(raw, st[2] + 10_000_000, st[5] - 20_000_000)  # 180 ms without odometry around frames 3, 4
    out, ctx = run_ingest(raw, tmp_path, odom_tolerance_ms=30)
    assert ctx.summary["skipped_no_odometry"] == 2
    assert out["frames"]["stamp_ns"].tolist() == [s for i, s in enumerate(st) if i not in (3, 4)]
    out, ctx = run_ingest(raw, tmp_path, odom_tolerance_ms=100)  # a 180 ms gap is within 2 x 100 ms
    assert ctx.summary["skipped_no_odometry"] == 0 and len(out["frames"]) == 8


def test_bad_input_window_whose_every_frame_was_skipped(raw, tmp_path):
    # the odometry misses the stretch around labelled frame 2: its frames are skipped, the label is counted
    # as lost, and windows are cut from the frames that exist (no window around the lost label)
    st = stamps_of(raw)
    drop_odometry(raw, st[0] + 10_000_000, st[4] - 20_000_000)
    out, ctx = run_ingest(raw, tmp_path, odom_tolerance_ms=30)
    assert ctx.summary["skipped_no_odometry"] == 3 and ctx.summary["labelled_frames_not_ingested"] == 1
    assert any(f"{st[2]} ns" in n for n in ctx.summary["notes"])
    frames = out["frames"]
    wctx = StageContext(stage="windows", seq="t", data_root=tmp_path, show_progress=False)
    w = windows.run({"frames": frames}, windows.Config(half_width=1, min_overlap=1), wctx)["windows"]
    assert set(w.frame_id) == set(frames.frame_id) and w[w.is_center].frame_id.tolist() == \
        frames[frames.labelled].frame_id.tolist() == [frames.index[frames.stamp_ns == st[5]][0]]


def test_bad_input_empty_odometry_csv_is_an_error(raw, tmp_path):
    (raw / "odometry.csv").write_text("timestamp,tx,ty,tz,qx,qy,qz,qw\n")
    with pytest.raises(IngestError, match=r"odometry.csv has no odometry rows"):
        run_ingest(raw, tmp_path)
    (raw / "odometry.csv").write_text("")
    with pytest.raises(IngestError, match=r"odometry.csv is not a readable CSV"):
        run_ingest(raw, tmp_path)


def test_bad_input_nan_in_odometry_rows_are_dropped_and_counted(raw, tmp_path):
    odo = pd.read_csv(raw / "odometry.csv")
    odo.loc[5, "tx"] = np.nan
    odo.loc[9, "qw"] = np.inf
    odo.to_csv(raw / "odometry.csv", index=False)
    out, ctx = run_ingest(raw, tmp_path)
    assert ctx.summary["odometry_rows_non_finite"] == 2 and len(out["frames"]) == 8
    assert np.isfinite(out["frames"][["tx", "ty", "tz", "qw"]].to_numpy()).all()


def test_bad_input_odometry_timestamp_that_is_not_a_time_is_an_error(raw, tmp_path):
    odo = pd.read_csv(raw / "odometry.csv", dtype={"timestamp": str})
    odo.loc[4, "timestamp"] = "12:00:03"
    odo.to_csv(raw / "odometry.csv", index=False)
    with pytest.raises(IngestError, match=r"odometry.csv, data row 5: timestamp '12:00:03' is not a time"):
        run_ingest(raw, tmp_path)


def test_bad_input_colour_image_not_named_by_a_stamp_is_an_error(raw, tmp_path):
    shutil.copy(next((raw / "rgb").iterdir()), raw / "rgb" / "frame_0001.png")
    with pytest.raises(IngestError, match=r"rgb/frame_0001.png: cannot read a timestamp .* every image in .*rgb must "
                                          r"be named by its timestamp"):
        run_ingest(raw, tmp_path)


# --- images ----------------------------------------------------------------------------------------

def test_bad_input_depth_of_another_size_than_colour_is_an_error_naming_both_files(raw, tmp_path):
    st = stamps_of(raw)[2]
    cv2.imwrite(str(raw / "depth" / f"{st}.png"), np.full((16, 24), 700, np.uint16))
    with pytest.raises(IngestError, match=rf"frame at {st} ns \(.*rgb/{st}.png and .*depth/{st}.png\): depth is "
                                          rf"24x16 but colour is 48x32"):
        run_ingest(raw, tmp_path)


def test_bad_input_8_bit_depth_png_is_a_counted_skip(raw, tmp_path):
    st = stamps_of(raw)[6]
    cv2.imwrite(str(raw / "depth" / f"{st}.png"), np.full((32, 48), 70, np.uint8))
    out, ctx = run_ingest(raw, tmp_path)
    assert ctx.summary["skipped_bad_image"] == 1 and len(out["frames"]) == 7
    assert f"depth/{st}.png: expected 16-bit single-channel, got uint8" in ctx.summary["notes"][0]


# --- params.yaml and annotations -------------------------------------------------------------------

def edit_params(raw: Path, **kv) -> None:
    p = yaml.safe_load((raw / "params.yaml").read_text())
    p.update(kv)
    (raw / "params.yaml").write_text(yaml.safe_dump(p))


def test_bad_input_params_k_not_3x3_is_an_error(raw, tmp_path):
    edit_params(raw, K=[[30.0, 0.0], [0.0, 30.0]])
    with pytest.raises(IngestError, match=r"params.yaml: K must be a 3x3 intrinsics matrix .* got shape \(2, 2\)"):
        run_ingest(raw, tmp_path)


@pytest.mark.parametrize("t, message", [
    (np.diag([2.0, 2.0, 2.0, 1.0]), r"rotation part is not orthonormal with determinant \+1"),
    (np.diag([1.0, 1.0, -1.0, 1.0]), r"det R = -1"),
    (np.vstack([np.eye(4)[:3], [[0, 0, 1, 1]]]), r"its last row is \[0.0, 0.0, 1.0, 1.0\]"),
    (np.eye(3), r"T_robot_camera must be a 4x4 matrix, got shape \(3, 3\)"),
])
def test_bad_input_params_extrinsics_not_rigid_is_an_error(raw, tmp_path, t, message):
    edit_params(raw, T_robot_camera=t.tolist())
    with pytest.raises(IngestError, match=r"params.yaml: .*" + message):
        run_ingest(raw, tmp_path)


def test_bad_input_missing_params_yaml_is_an_error(raw, tmp_path):
    (raw / "params.yaml").unlink()
    with pytest.raises(IngestError, match=r"params.yaml not found: expected params.yaml with K \(3x3\)"):
        run_ingest(raw, tmp_path, source="png")


def test_bad_input_annotation_with_a_class_id_the_table_lacks_is_an_error(raw, tmp_path):
    ann = json.loads((raw / "annotations.json").read_text())
    ann["annotations"][1]["category_id"] = 9
    (raw / "annotations.json").write_text(json.dumps(ann))
    with pytest.raises(IngestError, match=rf"annotations.json: annotation id {ann['annotations'][1]['id']} "
                                          rf"\(image_id \d+\) has category_id 9, which neither the class table "
                                          rf"nor the file's categories \[0, 1, 2, 3, 4\] have"):
        run_ingest(raw, tmp_path)
    # a dataset's own categories (listed in the file) are counted: the file then only says which frames are labelled
    ann["categories"].append({"id": 9, "name": "pepper_yellow"})
    (raw / "annotations.json").write_text(json.dumps(ann))
    out, ctx = run_ingest(raw, tmp_path)
    assert ctx.summary["annotation_categories_not_in_class_table"] == 1 and out["frames"]["labelled"].sum() == 2


def test_bad_input_annotations_for_a_frame_that_does_not_exist_are_counted(raw, tmp_path):
    ann = json.loads((raw / "annotations.json").read_text())
    ann["images"].append({"id": 99, "file_name": "rgb/1700000000000000000.png", "width": 48, "height": 32})
    (raw / "annotations.json").write_text(json.dumps(ann))
    out, ctx = run_ingest(raw, tmp_path)
    assert ctx.summary["labelled_frames_not_ingested"] == 1 and out["frames"]["labelled"].sum() == 2


def test_bad_input_detector_folder_with_semantic_pngs_only_is_an_error(raw, tmp_path):
    shutil.rmtree(raw / "pred_seg" / "instance")
    (raw / "pred_seg" / "scores.csv").unlink()
    with pytest.raises(IngestError, match=r"pred_seg has semantic/ but neither instance/ \(the png_pair format\) nor "
                                          r"a COCO detections JSON; the folder has: \['semantic/'\]"):
        run_ingest(raw, tmp_path)


def test_bad_input_detections_json_named_that_is_not_detections_is_an_error(raw, tmp_path):
    coco_row(raw)
    (raw / "pred_seg" / "other.json").write_text(json.dumps({"info": "not detections"}))
    with pytest.raises(IngestError, match=r"other.json is not a coco_panoptic file: expected a dict whose annotations "
                                          r"carry segments_info; it is a dict"):
        run_ingest(raw, tmp_path, detections_json="other.json", detections_format="coco_panoptic")


def test_bad_input_every_colour_image_corrupt_is_an_error_with_the_first_cause(raw, tmp_path):
    for p in (raw / "rgb").iterdir():
        p.write_bytes(p.read_bytes()[:50])
    with pytest.raises(IngestError, match=r"none of the 8 paired frames could be decoded; the first error: colour "
                                          r"image .*rgb/\d+.png is not a readable PNG"):
        run_ingest(raw, tmp_path)
