"""Fixtures: one tiny synthetic recording written as a PNG folder, a ROS 1 bag, ROS 2 sqlite3 and mcap bags."""
from pathlib import Path

import pytest

from pipeline.stage import StageContext
from stages import synth


@pytest.fixture(scope="session")
def tiny_raw(tmp_path_factory) -> Path:
    """data/raw/tiny with rgb/, depth/, odometry.csv, params.yaml, pred_seg/, annotations.json, gt/ and tiny.bag."""
    root = tmp_path_factory.mktemp("data")
    raw = root / "raw" / "tiny"
    raw.mkdir(parents=True)
    ctx = StageContext(stage="synth", seq="tiny", data_root=root, staging={"raw": raw}, show_progress=False)
    synth.run({}, synth.Config(n_frames=8, width=48, height=32, n_labelled=2, workers=1, supersample=1, seed=3), ctx)
    return raw


@pytest.fixture(scope="session")
def ros2_bags(tiny_raw, tmp_path_factory) -> dict[str, Path]:
    from rosbags.convert import convert
    from rosbags.typesys import Stores, get_typestore

    out = {}
    base = tmp_path_factory.mktemp("ros2")
    for storage in ("sqlite3", "mcap"):
        dst = base / f"tiny_{storage}"
        convert([tiny_raw / "tiny.bag"], dst, storage, 8, None, "file", get_typestore(Stores.ROS2_HUMBLE), None,
                [], [], [], [])
        out[storage] = dst
    return out
