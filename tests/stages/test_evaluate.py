import pandas as pd
import pytest

from rowmap.scoring import image_pixels_for, reference_pixels
from stages.evaluate import Config, countable_fruits


def test_countable_fruits_need_enough_pixels_in_enough_frames_of_the_near_row():
    rows = []
    for f in range(5):
        rows.append((f, 1, 300, True))         # near fruit 1: seen in 5 frames
        rows.append((f, 9, 300, True))         # fruit 9: far row (not in near_ids)
    rows += [(0, 2, 240, True), (1, 2, 97, True)]                      # glimpsed at the start: 2 frames
    rows += [(2, 3, 50, True), (3, 3, 8, True), (4, 3, 40, True)]      # 8 px in one frame: 2 visible frames
    rows += [(0, 4, 60, False), (1, 4, 60, True), (2, 4, 60, True), (3, 4, 60, True)]  # one view dropped
    seg = pd.DataFrame(rows, columns=["frame_id", "instance_id", "area_px", "kept"])
    cfg = Config(min_frames_id=3, min_visible_px=12)
    assert countable_fruits(seg, {1, 2, 3, 4}, 320 * 180, cfg) == [1, 4]
    assert countable_fruits(seg, {1, 2, 3, 4}, 320 * 180, Config(min_frames_id=2, min_visible_px=12)) == [1, 2, 3, 4]
    # at 1280x720 a fruit must cover 16 times the pixels (192) to count as visible: the same views at 16 times
    # the pixels give the same fruits; at their own pixels only fruit 1 (300 px) stays
    big = seg.assign(area_px=seg.area_px * 16)
    assert countable_fruits(big, {1, 2, 3, 4}, 1280 * 720, cfg) == [1, 4]
    assert countable_fruits(seg, {1, 2, 3, 4}, 1280 * 720, cfg) == [1]   # 60 px of fruit 4 < 192
    assert countable_fruits(seg, {1, 2, 3, 4}, 64 * 40, cfg) == [1, 4]   # smaller images are not scaled up


def test_reference_pixels_and_their_inverse():
    assert reference_pixels(16 * 12, 1280 * 720) == 12 and reference_pixels(12, 64 * 40) == 12
    assert image_pixels_for(12, 1280 * 720) == 192 and image_pixels_for(12, 640 * 360) == 48
    assert image_pixels_for(12, 320 * 180) == 12 and image_pixels_for(12, 64 * 40) == 12
    for px in (12, 7, 100):
        for size in (320 * 180, 1280 * 720, 1000 * 700):
            assert reference_pixels(image_pixels_for(px, size), size) >= px
            assert reference_pixels(image_pixels_for(px, size) - 1, size) < px


def test_images_scored_apart_and_added_equal_one_running_score():
    """evaluate scores frames on worker threads (PanopticScore.image) and adds them in frame order: the same
    PQ, mIoU and ID consistency as one score updated frame by frame."""
    from concurrent.futures import ThreadPoolExecutor

    import numpy as np

    from pipeline.classes import THING_IDS
    from rowmap.scoring import PanopticScore

    rng = np.random.default_rng(3)
    frames = []
    for _ in range(6):
        g_inst = np.zeros((40, 60), np.int64)
        g_sem = rng.choice([0, 1], size=(40, 60))
        for fruit in range(1, 5):
            v, u = rng.integers(0, 30), rng.integers(0, 50)
            g_inst[v:v + 10, u:u + 10] = fruit
            g_sem[v:v + 10, u:u + 10] = THING_IDS[fruit % len(THING_IDS)]
        # the prediction: the fruits' ids renamed, some pixels flipped, one fruit merged into another
        p_inst = np.where(g_inst > 0, g_inst + 10, 0)
        p_inst[p_inst == 14] = 13 if rng.random() < 0.5 else 14
        p_sem = np.where(rng.random(g_sem.shape) < 0.1, rng.choice([0, 1], size=g_sem.shape), g_sem)
        frames.append((p_sem, p_inst, g_sem, g_inst, np.arange(1, 5)))
    running = PanopticScore(1)
    for f in frames:
        running.update(*f)
    added = PanopticScore(1)
    with ThreadPoolExecutor(3) as pool:
        for one in pool.map(lambda f: added.image(*f), frames):
            added.add(one)
    a, b = running.metrics(2), added.metrics(2)
    assert a.keys() == b.keys() and a["id_consistency_n_fruits"] == 4
    for k in a:
        assert b[k] == pytest.approx(a[k], nan_ok=True), k
    assert added.n == 6 and (added.conf.matrix == running.conf.matrix).all() and added.ids == running.ids
    # a score that never saw an image adds nothing
    empty = PanopticScore(1)
    added.add(empty)
    assert added.metrics(2) == b
