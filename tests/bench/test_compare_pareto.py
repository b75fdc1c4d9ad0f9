import numpy as np
import pandas as pd
import pytest

from bench.compare import markdown, summary
from bench.pareto import pareto_front


def test_pareto_front_keeps_only_undominated_points():
    cost = np.array([1.0, 2.0, 3.0, 3.0, 0.5])
    quality = np.array([10.0, 9.0, 12.0, 11.0, np.nan])
    np.testing.assert_array_equal(pareto_front(cost, quality), [True, False, True, False, False])


def test_compare_table_means_windows_and_reports_skips():
    rows = []
    for wid, psnr in ((0, 20.0), (1, 22.0)):
        common = dict(window=wid, val_frames=3, threads=2, settings="quick", seq="s")
        rows.append(dict(method="detector input", poses="-", status="ok", note="", pq=0.8, miou=0.7, **common))
        rows.append(dict(method="ours cpu", poses="online refinement", status="ok", note="", psnr=psnr, pq=0.6,
                         miou=0.7, id_consistency=0.5, fit_min_per_window=1.0, render_s_per_image=2.0, params=10,
                         colour_steps=100, panoptic_steps=50, **common))
        rows.append(dict(method="ours cpu", poses="COLMAP", status="skipped", note="no colmap_poses", **common))
    df = pd.DataFrame(rows)
    s = summary(df).set_index("poses")
    assert s.loc["online refinement", "psnr"] == 21.0
    assert s.loc["COLMAP", "status"] == "skipped"
    md = markdown(df)
    assert "| ours cpu | online refinement | 21.00 | 60.0% |" in md
    assert "skipped: no colmap_poses" in md and "colour steps 100" in md


def test_pareto_image_scale_halves_images_labels_truth_and_intrinsics():
    from bench.pareto import downscale
    from nerf.panoptic.labels import WindowLabels
    from nerf.window import WindowData

    img = np.zeros((1, 4, 6, 3), np.uint8)
    img[0, :, :2] = 200                                   # left third bright
    sem = np.zeros((1, 4, 6), np.uint8)
    sem[0, :, 4:] = 2
    data = WindowData(img, np.full((1, 4, 6), 0.5, np.float32), np.array([[10.0, 10.0, 3.0, 2.0]]),
                      np.eye(4)[None], np.array([True]), np.array([7]))
    labels = WindowLabels(sem, (sem > 0).astype(np.int32))
    d, lab, gts = downscale(data, labels, [(sem[0], sem[0].astype(np.int32))], 0.5)
    assert d.images.shape == (1, 2, 3, 3) and (d.images[0, :, 0] == 200).all() and (d.images[0, :, 1:] == 0).all()
    np.testing.assert_allclose(d.intrinsics, [[5.0, 5.0, 1.5, 1.0]])
    assert lab.semantic.shape == (1, 2, 3) and (lab.semantic[0, :, 2] == 2).all() and (lab.instance[0, :, :2] == 0).all()
    assert gts[0][0].shape == (2, 3) and downscale(data, labels, gts, 1.0)[0] is data


def test_kept_frames_keeps_every_training_frame_and_spreads_the_validation_ones():
    from bench._common import kept_frames

    is_train = np.array([0, 1, 0, 1, 0, 1, 0, 1, 0], bool)
    assert kept_frames(is_train, None).tolist() == list(range(9))
    assert kept_frames(is_train, 0).tolist() == [1, 3, 5, 7]
    assert kept_frames(is_train, 2).tolist() == [0, 1, 3, 5, 7, 8]


def test_window_count_counts_distinct_ids_so_flicker_overcounts_and_merges_undercount():
    from bench.ablation import window_count
    from pipeline.classes import THING_IDS

    thing = THING_IDS[0]

    def frame(segments: dict[int, slice]) -> tuple[np.ndarray, np.ndarray]:
        sem = np.zeros((10, 40), np.uint8)
        inst = np.zeros((10, 40), np.int32)
        for i, cols in segments.items():
            sem[:, cols], inst[:, cols] = thing, i
        return sem, inst

    gts = [frame({1: slice(0, 5), 2: slice(10, 15)}), frame({1: slice(2, 7), 2: slice(12, 17)})]
    same = [frame({5: slice(0, 5), 9: slice(10, 15)}), frame({5: slice(2, 7), 9: slice(12, 17)})]
    assert window_count(same, gts, 12) == {"count_pred": 2.0, "count_gt": 2.0, "count_error_rel": 0.0}
    flicker = [frame({5: slice(0, 5), 9: slice(10, 15)}), frame({6: slice(2, 7), 9: slice(12, 17)})]
    assert window_count(flicker, gts, 12)["count_error_rel"] == 0.5          # fruit 1 counted twice
    merged = [frame({5: slice(0, 15)}), frame({5: slice(2, 17)})]
    assert window_count(merged, gts, 12)["count_pred"] == 1.0
    tiny = [frame({5: slice(0, 5), 8: slice(30, 31)}), frame({5: slice(2, 7)})]   # 10 px of id 8: too small
    assert window_count(tiny, gts, 12)["count_pred"] == 1.0
    stuff = [(np.zeros((10, 40), np.uint8), inst) for _, inst in same]       # ids on stuff pixels are no fruit
    assert window_count(stuff, gts, 12)["count_pred"] == 0.0


def test_resize_nearest_takes_each_pixel_label_at_its_centre_for_any_dtype():
    from bench.compare import resize_nearest

    a = np.arange(8 * 12, dtype=np.int64).reshape(8, 12)       # cv2 cannot resize int64
    small = resize_nearest(a, (2, 3))
    assert small.dtype == np.int64
    np.testing.assert_array_equal(small, a[[2, 6]][:, [2, 6, 10]])
    np.testing.assert_array_equal(resize_nearest(a, a.shape), a)


def test_stage_points_vary_only_the_cost_and_rates_of_nerf_fit_settings():
    from bench.pareto import MODES, STAGE_POINTS
    from nerf.config import NerfConfig

    assert STAGE_POINTS[0][2] == {} and MODES["stage"]["val_frames"] == 0    # the reference: the stage unchanged
    knobs = {"steps_factor", "step_factor", "train_early_stop", "lr_grid", "lr_mlp", "log2_capacity", "hidden"}
    for _, preset_name, change in STAGE_POINTS[1:]:
        assert preset_name == "" and change and set(change) <= knobs
        fields = {k: v for k, v in change.items() if k in NerfConfig.__dataclass_fields__}
        assert all(getattr(NerfConfig(), k) != v for k, v in fields.items())   # each point changes what it names


def test_fronts_of_two_runs_count_renders_in_the_window_minutes_and_plot(tmp_path):
    from bench.pareto import main

    def run(fit, render_s, psnr, pq):
        return pd.DataFrame({"point": ["a", "b", "c"], "fit_min_per_window": fit, "render_s_per_image": render_s,
                             "val_frames": 30, "psnr": psnr, "pq": pq, "count_pred": 18.0, "count_gt": 18.0,
                             "seq": "s", "window": 0})

    old = run([2.0, 1.5, 1.0], [2.0, 2.0, 2.0], [28.7, 28.0, 27.4], [.90, .89, .91])
    new = run([1.5, 1.1, 0.8], [1.0, 1.0, 1.0], [28.7, 28.0, 27.4], [.90, .89, .91])
    old.to_parquet(tmp_path / "old.parquet")
    new.to_parquet(tmp_path / "new.parquet")
    assert main(["--fronts", f"old={tmp_path / 'old.parquet'}", f"new={tmp_path / 'new.parquet'}",
                 "--out", str(tmp_path / "out")]) == 0
    df = pd.read_parquet(tmp_path / "out" / "pareto_fronts.parquet")
    np.testing.assert_allclose(df[df.code == "old"].window_min, [3.0, 2.5, 2.0])  # 30 renders of 2 s = 1 min
    np.testing.assert_allclose(df[df.code == "new"].window_min, [2.0, 1.6, 1.3])
    assert df[df.code == "old"].front_pq.tolist() == [False, False, True]  # c is cheapest and best in PQ
    assert df.front_psnr.all()
    assert (tmp_path / "out" / "pareto_fronts.png").stat().st_size > 10_000
    with pytest.raises(SystemExit):
        main(["--fronts", str(tmp_path / "old.parquet")])  # no label
    with pytest.raises(SystemExit):
        main(["--fronts", f"old={tmp_path / 'missing.parquet'}"])
