"""The render contract: what nerf_fit writes (write_frame) is what the readers get back (Renders.read)."""
import numpy as np
import pandas as pd
import pytest
import torch

from pipeline.images import ImageError
from rowmap import renders


def test_written_renders_read_back_through_the_table(tmp_path):
    rng = np.random.default_rng(0)
    h, w = 5, 7
    images = {"rgb": torch.from_numpy(rng.uniform(-0.2, 1.2, (h, w, 3)).astype(np.float32)),
              "depth": torch.from_numpy(rng.uniform(0.0, 3.0, (h, w)).astype(np.float32)),
              "semantic": rng.integers(0, 5, (h, w)), "instance": rng.integers(0, 40000, (h, w)),
              "fruit": rng.uniform(0.0, 1.0, (h, w)).astype(np.float32)}
    nerf = tmp_path / "processed" / "seq" / "nerf"
    rows = renders.write_frame(nerf, 3, 12, images)
    assert [r["kind"] for r in rows] == list(renders.KINDS)
    assert rows[0]["file"] == "window_003/renders/rgb_000012.png"
    table = pd.DataFrame([{**{k: r[k] for k in ("window_id", "frame_id", "kind")},
                           "path": f"processed/seq/nerf/{r['file']}"} for r in rows])
    got = renders.Renders(table, tmp_path)
    assert got.has(3, 12, *renders.KINDS) and not got.has(3, 13, "rgb") and got.frames(3, "depth") == {12}
    rgb = got.read(3, 12, "rgb", (h, w))
    np.testing.assert_array_equal(rgb, (np.clip(images["rgb"].numpy(), 0, 1) * 255).round().astype(np.uint8))
    depth = got.read(3, 12, "depth", (h, w))
    assert np.abs(depth - images["depth"].numpy()).max() <= 0.5 * renders.DEPTH_SCALE_M + 1e-6   # mm rounding
    np.testing.assert_array_equal(got.read(3, 12, "semantic"), images["semantic"])
    np.testing.assert_array_equal(got.read(3, 12, "instance"), images["instance"])
    assert np.abs(got.read(3, 12, "fruit") - images["fruit"]).max() <= 0.5 / 255 + 1e-6   # 8-bit rounding


def test_a_render_not_in_the_table_or_of_another_size_is_an_error(tmp_path):
    rows = renders.write_frame(tmp_path / "nerf", 0, 4, {"rgb": np.zeros((4, 6, 3)), "depth": np.ones((4, 6))})
    table = pd.DataFrame([{"window_id": r["window_id"], "frame_id": r["frame_id"], "kind": r["kind"],
                           "path": f"nerf/{r['file']}"} for r in rows])
    got = renders.Renders(table, tmp_path)
    with pytest.raises(ImageError, match=r"window 0, frame 4: no semantic render .*\['depth', 'rgb'\]"):
        got.read(0, 4, "semantic")
    with pytest.raises(ImageError, match="6x4, frames.parquet says 8x4"):
        got.read(0, 4, "depth", (4, 8))
    with pytest.raises(ValueError, match="unknown render kind 'normal'"):
        renders.file_name(0, "normal", 4)
