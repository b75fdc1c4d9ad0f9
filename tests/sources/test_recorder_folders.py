"""A recorder's own folder brought into the layout: timestamps in other units, depth in other units, JPEG
colour, stray files. Each case is read right, or stops with an error naming the file and the setting."""
import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import pytest
import yaml

from raw_helpers import copy_raw
from test_detector_formats import run_ingest
from sources.common import IngestError, read_stamp
from stages import synth

STAMPED_FOLDERS = ("rgb", "depth", "seg", "pred_seg/semantic", "pred_seg/instance", "gt/semantic", "gt/instance")


@pytest.fixture
def raw(tiny_raw, tmp_path) -> Path:
    return copy_raw(tiny_raw, tmp_path)


def stamps_of(raw: Path) -> list[int]:
    return sorted(int(p.stem) for p in (raw / "rgb").iterdir())


def restamp(raw: Path, new_ns, name) -> None:
    """Every stamp of the row moved to new_ns(old ns): file names written by name(new ns), odometry.csv's
    timestamps likewise; scores.csv and gt/poses.parquet keep integer ns."""
    for sub in STAMPED_FOLDERS:
        for p in sorted((raw / sub).glob("*.png")):
            p.rename(p.with_name(f"{name(new_ns(int(p.stem)))}.png"))
    odo = pd.read_csv(raw / "odometry.csv", dtype={"timestamp": str})
    odo["timestamp"] = [name(new_ns(int(t))) for t in odo["timestamp"]]
    odo.to_csv(raw / "odometry.csv", index=False)
    scores = pd.read_csv(raw / "pred_seg" / "scores.csv")
    scores.assign(stamp_ns=[new_ns(int(s)) for s in scores.stamp_ns]).to_csv(raw / "pred_seg" / "scores.csv",
                                                                              index=False)
    ann = json.loads((raw / "annotations.json").read_text())
    for img in ann["images"]:
        img["file_name"] = f"rgb/{name(new_ns(int(Path(img['file_name']).stem)))}.png"
    (raw / "annotations.json").write_text(json.dumps(ann))
    poses = pd.read_parquet(raw / "gt" / "poses.parquet")
    poses.assign(stamp_ns=[new_ns(int(s)) for s in poses.stamp_ns]).to_parquet(raw / "gt" / "poses.parquet")


def since_boot(at_ns: int):
    """Stamps of a clock counting from boot: the row's odometry starts at_ns after boot."""
    return lambda ns: ns - (synth.FIRST_STAMP_NS - 200_000_000) + at_ns


# --- timestamps ------------------------------------------------------------------------------------

@pytest.mark.parametrize("name, unit, ns, how", [
    ("1600000000123456789", "auto", 1_600_000_000_123_456_789, "ns"),
    ("999999999999999999", "auto", 999_999_999_999_999_999, "ns"),         # 18 digits: ns whatever the date
    ("1600000000123456", "auto", 1_600_000_000_123_456_000, "us"),
    ("1600000000123", "auto", 1_600_000_000_123_000_000, "ms"),
    ("1600000000", "auto", 1_600_000_000_000_000_000, "s"),
    ("100.033333333", "auto", 100_033_333_333, "decimal s"),               # decimal seconds from any origin
    ("1600000000.5", "auto", 1_600_000_000_500_000_000, "decimal s"),
    ("123456789012", "ns", 123_456_789_012, "ns"),
    ("1600000000123", "ns", 1_600_000_000_123, "ns"),
    ("1600000000123.5", "ms", 1_600_000_000_123_500_000, "ms"),
    ("42", "s", 42_000_000_000, "s"),
])
def test_stamp_units_read(name, unit, ns, how):
    assert read_stamp(name, unit) == (ns, how)


@pytest.mark.parametrize("name", [
    "123456789012",          # 12 digits: ns of a clock 2 min after boot, or ms of 1973
    "12345678901234567",     # 17 digits
    "9999999999999",         # 13 digits, but as ms after 2100
    "999999999",             # 9 digits
    "7",                     # a frame counter
    "1600000000123456.5",    # as decimal seconds after 2100
    "4200000000000000000",   # 19 digits after 2100
])
def test_bad_input_stamp_whose_unit_is_in_doubt_needs_stamp_unit(name):
    with pytest.raises(IngestError, match=r"cannot tell the unit .* set ingest.stamp_unit"):
        read_stamp(name, "auto")


def test_stamp_read_in_a_unit_that_overflows_is_an_error():
    with pytest.raises(IngestError, match=r"read in s \(ingest.stamp_unit\) lies after the year 2262"):
        read_stamp("1600000000123456789", "s")


def test_bad_input_boot_clock_ns_names_are_an_error_or_read_with_stamp_unit(raw, tmp_path):
    ref, _, _ = run_ingest(raw, tmp_path)
    restamp(raw, since_boot(200_000_000_000), str)   # 12-digit ns names, 200 s after boot
    with pytest.raises(IngestError, match=r"odometry.csv, data row 1: timestamp '200000000000' is not a time: "
                                          r"cannot tell the unit .* set ingest.stamp_unit"):
        run_ingest(raw, tmp_path)
    out, ctx, _ = run_ingest(raw, tmp_path, stamp_unit="ns")
    assert out["frames"]["stamp_ns"].tolist() == [since_boot(200_000_000_000)(s) for s in ref["frames"]["stamp_ns"]]
    assert out["frames"]["labelled"].tolist() == ref["frames"]["labelled"].tolist()
    assert out["frames"]["gt_instance_path"].notna().all()
    pd.testing.assert_frame_equal(out["detections"], ref["detections"])
    cols = ["tx", "ty", "tz", "qx", "qy", "qz", "qw"]
    np.testing.assert_allclose(out["frames"][cols].to_numpy(), ref["frames"][cols].to_numpy(), atol=1e-9)


def test_bad_input_boot_clock_ns_names_that_look_like_ms_are_an_error(raw, tmp_path):
    # 13-digit ns names (1000 s after boot) look like ms since the epoch (2001); read so, the frames would
    # lie 18 hours apart: an error, not a silent misreading
    restamp(raw, since_boot(1_000_000_000_000), str)
    with pytest.raises(IngestError, match=r"odometry.csv, column timestamp: the names read as ms .* lie a median "
                                          r"2e\+04 s apart.* set ingest.stamp_unit"):
        run_ingest(raw, tmp_path)
    out, _, _ = run_ingest(raw, tmp_path, stamp_unit="ns")
    assert len(out["frames"]) == 8 and out["frames"]["labelled"].sum() == 2


def test_names_in_epoch_ms_are_read_as_ms(raw, tmp_path):
    # a recorder writing ms since the epoch (13 digits): read as such without a setting
    restamp(raw, lambda ns: ns // 1_000_000 * 1_000_000, lambda ns: str(ns // 1_000_000))
    out, _, _ = run_ingest(raw, tmp_path)
    assert len(out["frames"]) == 8 and out["frames"]["labelled"].sum() == 2
    assert (out["frames"]["stamp_ns"] % 1_000_000 == 0).all() and out["frames"]["stamp_ns"].iloc[0] == \
        synth.FIRST_STAMP_NS


def test_bad_input_odometry_stamps_in_another_unit_than_the_names(raw, tmp_path):
    odo = pd.read_csv(raw / "odometry.csv", dtype={"timestamp": str})
    odo["timestamp"] = [str(int(t) - synth.FIRST_STAMP_NS + 10**12) for t in odo["timestamp"]]
    odo.to_csv(raw / "odometry.csv", index=False)
    with pytest.raises(IngestError, match=r"odometry.csv.* ingest.stamp_unit"):
        run_ingest(raw, tmp_path)


# --- depth scale -----------------------------------------------------------------------------------

def edit_params(raw: Path, **kv) -> None:
    p = yaml.safe_load((raw / "params.yaml").read_text())
    p.update(kv)
    (raw / "params.yaml").write_text(yaml.safe_dump(p))


def depth_images(staging: Path, frames: pd.DataFrame) -> np.ndarray:
    return np.stack([cv2.imread(str(staging / "depth" / Path(p).name), cv2.IMREAD_UNCHANGED)
                     for p in frames["depth_path"]]).astype(np.int64)


def test_bad_input_depth_png_in_tenths_of_a_millimetre_follows_depth_scale_m(raw, tmp_path):
    ref, _, ref_dir = run_ingest(raw, tmp_path)
    for p in (raw / "depth").glob("*.png"):
        mm = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        cv2.imwrite(str(p), (mm.astype(np.int64) * 10).clip(0, 65535).astype(np.uint16))
    edit_params(raw, depth_scale_m=0.0001)
    out, _, out_dir = run_ingest(raw, tmp_path)
    want = depth_images(ref_dir, ref["frames"])
    want[want * 10 > 65535] = 0   # beyond 6.5 m a tenth-of-a-millimetre PNG cannot hold the depth
    assert np.array_equal(depth_images(out_dir, out["frames"]), want)


def test_bag_16uc1_depth_follows_depth_scale_m_of_params_yaml_beside_it(tiny_raw, tmp_path):
    raw = copy_raw(tiny_raw, tmp_path, drop_png_layout=True)
    ref, _, ref_dir = run_ingest(raw, tmp_path)
    edit_params(raw, depth_scale_m=0.002)
    out, _, out_dir = run_ingest(raw, tmp_path)
    want = depth_images(ref_dir, ref["frames"]) * 2
    assert np.array_equal(depth_images(out_dir, out["frames"]), np.where(want < 65535, want, 0))


@pytest.mark.parametrize("value", [0, -0.001, "mm", 2.0])
def test_bad_input_depth_scale_m_that_is_not_a_scale_is_an_error(raw, tmp_path, value):
    edit_params(raw, depth_scale_m=value)
    with pytest.raises(IngestError, match=r"params.yaml: depth_scale_m must be metres per unit .* in \(0, 1\]"):
        run_ingest(raw, tmp_path)


# --- JPEG colour and other files -------------------------------------------------------------------

def test_bad_input_jpeg_colour_frame_is_read_and_other_files_are_counted(raw, tmp_path):
    st = stamps_of(raw)[4]
    png = raw / "rgb" / f"{st}.png"
    cv2.imwrite(str(png.with_suffix(".jpg")), cv2.imread(str(png)), [cv2.IMWRITE_JPEG_QUALITY, 98])
    png.unlink()
    (raw / "rgb" / "notes.txt").write_text("recorder log")
    (raw / "depth" / "Thumbs.db").write_bytes(b"\0")
    out, ctx, staging = run_ingest(raw, tmp_path)
    assert len(out["frames"]) == 8 and st in out["frames"]["stamp_ns"].tolist()
    assert ctx.summary["skipped_no_depth"] == 0 and ctx.summary["files_not_images"] == 2
    notes = " ".join(ctx.summary["notes"])
    assert "rgb: 1 entry not PNG or JPEG images ignored: notes.txt" in notes
    assert "depth: 1 entry not PNG images ignored: Thumbs.db" in notes
    frame = out["frames"][out["frames"].stamp_ns == st].iloc[0]
    assert frame.rgb_path.endswith(f"rgb/{st}.png")   # extracted as PNG like every frame
    rgb = cv2.imread(str(staging / "rgb" / f"{st}.png")).astype(float)
    assert np.abs(rgb - cv2.imread(str(raw / "rgb" / f"{st}.jpg")).astype(float)).max() == 0


def test_bad_input_jpeg_depth_image_is_an_error_naming_it(raw, tmp_path):
    st = stamps_of(raw)[2]
    shutil.copy(raw / "rgb" / f"{st}.png", raw / "depth" / f"{st}.jpg")
    with pytest.raises(IngestError, match=rf"depth/{st}.jpg: depth images must be 16-bit PNGs"):
        run_ingest(raw, tmp_path)
