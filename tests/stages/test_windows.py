import pandas as pd
import pytest

from pipeline.stage import StageContext
from stages import windows


def frames(n, labelled):
    return pd.DataFrame({"frame_id": range(n), "labelled": [i in labelled for i in range(n)]})


def run(n, labelled, **cfg):
    cfg.setdefault("context_frames", 0)      # the windows' own spans; test_context_frames_only_train has them
    ctx = StageContext(stage="windows", seq="t", data_root=".", show_progress=False)
    return windows.run({"frames": frames(n, labelled)}, windows.Config(**cfg), ctx)["windows"], ctx


def test_one_window_per_labelled_frame_clipped_with_alternating_split():
    w, ctx = run(30, {2, 15}, half_width=5, cover_row=False, val_every=2)
    assert sorted(w["window_id"].unique()) == [0, 1]
    w0 = w[w.window_id == 0]
    assert w0["frame_id"].tolist() == list(range(0, 8))      # clipped at the start
    assert (w0.set_index("offset")["split"].loc[[-1, 1, 3]] == "train").all()
    assert (w0.set_index("offset")["split"].loc[[-2, 0, 2]] == "val").all()
    centre = w[w.is_center]
    assert centre["frame_id"].tolist() == [2, 15]
    assert ctx.summary["windows"] == 2


def test_shared_frames_have_one_role_in_every_window_and_centres_are_validation():
    w, _ = run(40, {10, 17}, half_width=6, cover_row=False, val_every=2)  # centres of opposite parity, overlapping
    roles = w.groupby("frame_id")["split"].nunique()
    assert (roles == 1).all()
    assert (w[w.is_center]["split"] == "val").all()
    w1 = w[w.window_id == 1].set_index("frame_id")["split"]
    assert w1.loc[17] == "val" and (w1.loc[[12, 14, 16, 18]] == "val").all() and (w1.loc[[13, 15, 19]] == "train").all()
    assert 0.4 <= (w1 == "train").mean() <= 0.6


def test_every_val_every_th_frame_validates_and_labelled_frames_always_do():
    w, _ = run(60, {10, 33}, half_width=8, cover_row=False, val_every=4)
    roles = w.drop_duplicates("frame_id").set_index("frame_id")["split"]
    val = set(roles[roles == "val"].index)
    # counted from the first centre (10): 2, 6, 10, 14, 18 and 26, 30, 34, 38, plus the labelled 33
    assert val == {2, 6, 10, 14, 18, 26, 30, 33, 34, 38} and (w.groupby("frame_id")["split"].nunique() == 1).all()
    assert (w[w.is_center].split == "val").all()
    default, _ = run(60, {10, 33}, half_width=8, cover_row=False)
    assert (default.split == "val").sum() == (w.split == "val").sum()     # 4 is the default
    with pytest.raises(ValueError, match="val_every must be >= 2"):
        windows.Config(val_every=1)


def test_overlap_is_recorded():
    w, ctx = run(30, {10, 14}, half_width=5, cover_row=False)
    n = w.drop_duplicates("frame_id").set_index("frame_id")["n_windows"]
    assert n.loc[12] == 2 and n.loc[5] == 1
    assert ctx.summary["frames_in_several_windows"] == len(range(9, 16))


def test_unlabelled_sequence_gets_evenly_spaced_windows_without_eval_frame():
    w, ctx = run(50, set(), half_width=5, cover_row=False)
    assert sorted(w["center_frame_id"].unique()) == [5, 15, 25, 35, 45]
    assert not w["is_center"].any()
    assert "no labelled frames" in ctx.summary["notes"][0]


def test_max_windows_spreads_evenly():
    w, _ = run(100, {10, 20, 30, 40, 50, 60, 70}, half_width=3, max_windows=3)
    assert sorted(w["center_frame_id"].unique()) == [10, 40, 70]


def test_bad_half_width():
    with pytest.raises(ValueError, match="half_width must be >= 1"):
        windows.Config(half_width=0)
    with pytest.raises(ValueError, match="min_overlap and windows.grow_overlap must be >= 0"):
        windows.Config(min_overlap=-1)
    with pytest.raises(ValueError, match="grow_overlap must be >= 0"):
        windows.Config(grow_overlap=-1)


def test_cover_row_extends_windows_into_short_gaps_and_fills_long_ones():
    # 120 frames, labelled 30 / 60 / 89 (the default row): the end windows grow to the sequence ends
    w, ctx = run(120, {30, 60, 89}, half_width=20)
    span = w.groupby("window_id").frame_id.agg(["min", "max"])
    assert span.values.tolist() == [[0, 51], [40, 80], [69, 119]]   # neighbours share min_overlap = 12
    assert ctx.summary["filler_windows"] == 0 and ctx.summary["frames_in_no_window"] == 0
    # 240 frames, labelled 60 / 120 / 179 (a longer row): the gaps of 18-19 frames between the windows are
    # closed by growing them (up to half_width per side), the 40 frames at either end get a filler window
    w, ctx = run(240, {60, 120, 179}, half_width=20)
    span = w.groupby("window_id").frame_id.agg(["min", "max"]).sort_values("min").to_numpy()
    assert ctx.summary["frames_in_no_window"] == 0 and ctx.summary["filler_windows"] == 2
    assert (span[1:, 0] <= span[:-1, 1] - 11).all()                  # neighbours share >= 12 frames
    assert w[w.is_center].frame_id.tolist() == [60, 120, 179]          # fillers have no evaluation frame
    assert (w.groupby("window_id").size() <= 41 + 2 * 20).all()      # extensions stay within max_extend
    # with max_extend = 10 the same gaps need 4 fillers
    _, small = run(240, {60, 120, 179}, half_width=20, max_extend=10)
    assert small.summary["filler_windows"] == 4 and small.summary["frames_in_no_window"] == 0
    roles = w.groupby("frame_id")["split"].nunique()
    assert (roles == 1).all() and (w[w.frame_id.isin([60, 120, 179])].split == "val").all()
    assert 0.7 <= (w.drop_duplicates("frame_id").split == "train").mean() <= 0.8   # val_every 4
    assert "filler window" in " ".join(ctx.summary["notes"])


def test_a_recording_with_a_labelled_frame_every_metre_needs_one_filler_per_end():
    # the bup20 layout: 450 frames, labelled every 75 frames: the five labelled windows grow into the 34-frame
    # gaps between them and one filler covers each end (7 windows; with max_extend = 10 it takes 13)
    w, ctx = run(450, {75, 150, 224, 299, 374}, half_width=20)
    span = w.groupby("window_id").frame_id.agg(["min", "max"]).sort_values("min").to_numpy()
    assert w.window_id.nunique() == 7 and ctx.summary["filler_windows"] == 2
    assert ctx.summary["frames_in_no_window"] == 0 and (span[1:, 0] <= span[:-1, 1] - 3).all()
    assert (w.groupby("window_id").size() <= 41 + 2 * 20).all()      # grow_overlap stays within max_extend


def test_neighbours_grow_to_share_grow_overlap_frames_where_max_extend_allows():
    # 180 frames labelled every 45 frames: the 41-frame windows nearly touch and grow to share 12 frames
    w, ctx = run(180, {22, 67, 112, 157}, half_width=20)
    span = w.groupby("window_id").frame_id.agg(["min", "max"]).sort_values("min").to_numpy()
    assert ctx.summary["filler_windows"] == 0
    assert (span[:-1, 1] - span[1:, 0] + 1).tolist() == [12, 12, 12]
    # without it they share min_overlap; a gap they cannot grow across leaves them at what max_extend allows
    w0, _ = run(180, {22, 67, 112, 157}, half_width=20, grow_overlap=0)
    span0 = w0.groupby("window_id").frame_id.agg(["min", "max"]).sort_values("min").to_numpy()
    assert (span0[:-1, 1] - span0[1:, 0] + 1).tolist() == [4, 4, 4]
    w3, ctx3 = run(160, {20, 60, 100, 140}, half_width=20, max_extend=3)     # windows [c-20, c+20] touch
    span3 = w3.groupby("window_id").frame_id.agg(["min", "max"]).sort_values("min").to_numpy()
    assert ctx3.summary["filler_windows"] == 0
    assert (span3[:-1, 1] - span3[1:, 0] + 1).tolist() == [7, 7, 7]     # 1 + 3 on each side at most
    assert (span3[1:-1, 1] - span3[1:-1, 0] + 1 <= 41 + 2 * 3).all()
    assert run(450, {75, 150, 224, 299, 374}, half_width=20, max_extend=10)[0].window_id.nunique() == 13


def test_cover_row_is_off_with_max_windows_and_paper_windows_leave_gaps():
    w, ctx = run(240, {60, 120, 179}, half_width=20, max_windows=2)
    assert w.window_id.nunique() == 2 and ctx.summary["frames_in_no_window"] > 0
    w, ctx = run(240, {60, 120, 179}, half_width=20, cover_row=False)
    assert w.window_id.nunique() == 3 and ctx.summary["frames_in_no_window"] == 240 - 3 * 41


def test_context_frames_only_train_and_keep_every_frame_in_one_role():
    plain, _ = run(120, {30, 60, 89}, half_width=20, val_every=2)
    w, ctx = run(120, {30, 60, 89}, half_width=20, context_frames=4, val_every=2)
    for wid, g in w.groupby("window_id"):
        own = plain[plain.window_id == wid]
        extra = g[~g.frame_id.isin(own.frame_id)]
        # the window's own frames are unchanged; beyond them only training frames, at most 4 frames out
        assert set(own.frame_id) <= set(g.frame_id) and (g[g.frame_id.isin(own.frame_id)].split.values ==
                                                          own.split.values).all()
        assert (extra.split == "train").all() and not extra.is_center.any()
        lo, hi = own.frame_id.min(), own.frame_id.max()
        assert ((extra.frame_id >= lo - 4) & (extra.frame_id <= hi + 4)).all()
        assert len(extra) == (lo > 0) * 2 + (hi < 119) * 2        # every other frame is a training one
    assert (w.groupby("frame_id")["split"].nunique() == 1).all()
    assert ctx.summary["context_train_frames"] == 8
    with pytest.raises(ValueError, match="context_frames must be >= 0"):
        windows.Config(context_frames=-1)
