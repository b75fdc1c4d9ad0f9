import pandas as pd

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
    assert countable_fruits(seg, {1, 2, 3, 4}, cfg) == [1, 4]
    assert countable_fruits(seg, {1, 2, 3, 4}, Config(min_frames_id=2, min_visible_px=12)) == [1, 2, 3, 4]
