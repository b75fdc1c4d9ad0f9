"""A row laid out as the public BUP20 release is (<root>/<date>/row<N>, annotations at the root) is found and
ingested: placed under data/raw/ as a nested sequence, or linked in under a plain sequence name. The frames have
the size of a recording (1280x720); the run goes as far as the windows (the NeRF stages at this size are
measured by `pag bench scale`, not in the test suite)."""
import json
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from pipeline import cli
from pipeline.runner import PipelineError, Runner
from pipeline.stage import StageContext
from stages import synth

N_FRAMES, N_LABELLED = 10, 2
WIDTH, HEIGHT = 1280, 720  # the size of a BUP20 (RealSense) frame


def bup20_release(tmp: Path) -> Path:
    """A BUP20-layout release root holding one row, 20200924/row3, made from a synthetic row: rgb/, depth/,
    seg/, pred_seg/, odometry.csv, rgbd_odom.csv, params.yaml; the COCO annotations at the root (shared by
    every row of the release); no ground truth of the synthetic kind (gt/) and no bag."""
    made = tmp / "synth_out"
    made.mkdir()
    ctx = StageContext(stage="synth", seq="made", data_root=tmp, staging={"raw": made}, show_progress=False)
    synth.run({}, synth.Config(n_frames=N_FRAMES, width=WIDTH, height=HEIGHT, n_labelled=N_LABELLED, workers=2,
                               supersample=1, write_bag=False, seed=5), ctx)
    root = tmp / "BUP20"
    row = root / "20200924" / "row3"
    row.mkdir(parents=True)
    for sub in ("rgb", "depth", "seg", "pred_seg"):
        shutil.copytree(made / sub, row / sub)
    for name in ("odometry.csv", "params.yaml"):
        shutil.copy(made / name, row / name)
    odo = pd.read_csv(made / "odometry.csv")
    odo["tx"] += 0.01  # the alternative odometry differs from the wheel odometry by 1 cm along the row
    odo.to_csv(row / "rgbd_odom.csv", index=False, float_format="%.9f")
    ann = json.loads((made / "annotations.json").read_text())
    # a frame of another row of the release
    other = {"id": 99, "file_name": "rgb/1500000000000000000.png", "width": WIDTH, "height": HEIGHT}
    ann["images"].append(other)
    (root / "annotations.json").write_text(json.dumps(ann))
    (root / "20201001" / "row2").mkdir(parents=True)  # another date of the release, not used
    return root


@pytest.fixture(scope="module")
def release(tmp_path_factory) -> Path:
    return bup20_release(tmp_path_factory.mktemp("bup20"))


def run_to_windows(data_root: Path, seq: str, *sets: str) -> int:
    args = ["all", "--seq", seq, "--data-root", str(data_root), "--no-progress", "--to", "windows",
            "--set", "windows.half_width=2", *[a for s in sets for a in ("--set", s)]]
    return cli.main(args)


def test_release_under_data_raw_runs_as_nested_sequence(release, tmp_path):
    data = tmp_path / "data"
    data.mkdir()
    shutil.copytree(release, data / "raw")  # the release root placed as data/raw/
    runner = Runner("20200924/row3", data)
    assert not runner.synthetic and "synth" not in [s.name for s in runner.active()]
    assert run_to_windows(data, "20200924/row3") == 0
    interim = data / "interim" / "20200924" / "row3"
    frames = pd.read_parquet(interim / "frames.parquet")
    assert len(frames) == N_FRAMES and int(frames.labelled.sum()) == N_LABELLED  # annotations found at the root
    assert (frames[["width", "height"]].to_numpy() == [WIDTH, HEIGHT]).all()
    assert frames.det_instance_path.notna().all()
    assert all((data / p).is_file() for p in frames.rgb_path)
    windows = pd.read_parquet(interim / "windows.parquet")
    assert windows.window_id.nunique() == N_LABELLED
    assert (interim / "_manifest" / "windows.json").is_file()
    assert not (data / "raw" / "20200924" / "row3" / "gt").exists()  # the release was not written into


def test_release_linked_in_under_a_plain_name_with_the_alternative_odometry(release, tmp_path):
    data = tmp_path / "data"
    (data / "raw").mkdir(parents=True)
    (data / "raw" / "bup20_row3").symlink_to(release / "20200924" / "row3", target_is_directory=True)
    assert run_to_windows(data, "bup20_row3") == 0
    wheel = pd.read_parquet(data / "interim" / "bup20_row3" / "frames.parquet")
    assert int(wheel.labelled.sum()) == N_LABELLED  # the root's annotations, through the link
    assert run_to_windows(data, "bup20_row3", "ingest.odometry_csv=rgbd_odom.csv") == 0
    rgbd = pd.read_parquet(data / "interim" / "bup20_row3" / "frames.parquet")
    assert np.allclose(rgbd.tx - wheel.tx, 0.01, atol=1e-6)


@pytest.mark.parametrize("seq", ["../row3", "/abs/row3", "a//b", "a/../b", ".hidden", "a/.b", "", "row3/", " row3",
                                 "a\\b"])
def test_sequence_names_cannot_leave_data_raw(seq, tmp_path):
    with pytest.raises(PipelineError, match="--seq must be a folder name"):
        Runner(seq, tmp_path)
