"""A real RGB-D recording through the whole DAG: 12 frames of SUN3D's office (tests/data/sun3d_office_12f, a
Xtion's colour, depth with holes and borders, and a reconstruction's poses), run by `pag bench real_rgbd`'s
function with a short fit. The far plane and ICP's depth limit come from the recording's depth, the fit
reaches a real PSNR, and nothing is counted."""
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import pytest

from bench import real_rgbd

pytestmark = pytest.mark.slow  # about 50 s: a 640x480 fit: `make test-slow`


ROW = Path(__file__).resolve().parents[1] / "data" / "sun3d_office_12f"
SHORT = ("nerf_fit.model.steps=100", "nerf_fit.panoptic.stuff_only_steps=10", "nerf_fit.workers=1",
         "nerf_fit.render_scale=0.25")


def test_real_office_excerpt_runs_end_to_end_with_depth_derived_range(tmp_path):
    root = tmp_path / "data"
    table = real_rgbd.run(ROW, root, overrides=SHORT, show_progress=False)
    seq = table.seq.iloc[0]
    first = table.iloc[0]
    assert first.count_pred == 0
    metrics = pd.read_parquet(root / "processed" / seq / "window_metrics.parquet")
    assert (metrics.status == "ok").all()
    # the far plane covers the recording's depth (99th percentile 5.9 m here, where the default row's is 3.5 m)
    depth = np.stack([cv2.imread(str(p), cv2.IMREAD_UNCHANGED) for p in sorted((ROW / "depth").glob("*.png"))])
    valid = depth[depth > 0] / 1000.0
    far = float(metrics.far_m.iloc[0])
    assert np.percentile(valid, 99) <= far <= 1.2 * np.percentile(valid, 99) + 0.5
    # ICP reaches past the 1.5 m that holds only ~1 % of this room's depth
    assert float(metrics.icp_max_depth_m.iloc[0]) >= 3.0
    assert (valid <= float(metrics.icp_max_depth_m.iloc[0])).mean() > 0.5
    # a real image fitted in 100 steps (PSNR at a quarter of the size): the space the sensor saw through is empty, so rays reach the surfaces
    assert first.psnr_db > 20, first.psnr_db
    assert first.samples_per_ray < 96
    assert np.isfinite(first.ate_odometry_m) and np.isfinite(first.ate_refined_m)
    stages = set(table.stage)
    assert {"ingest", "nerf_fit", "panoptic_fusion", "fruit_count", "evaluate", "total"} <= stages
    # the depth sensor as a referee of the poses: every set of poses gives a finite disagreement
    for name in ("odometry", "refined", "reference"):
        assert np.isfinite(first[f"depth_disagreement_{name}_mm"]), name
