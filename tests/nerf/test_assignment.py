import numpy as np
import pytest
import torch

from nerf.panoptic.assignment import OUTSIDE_COST, SlotWindow, along_track, assign, position_preference, segment_costs


def test_segment_costs_are_minus_mean_probability():
    probs = torch.tensor([[0.1, 0.9, 0.0], [0.1, 0.5, 0.4], [0.0, 0.0, 1.0]])
    cost = segment_costs(probs, torch.tensor([0, 0, 1]), 2)
    assert torch.allclose(cost, -torch.tensor([[0.1, 0.7, 0.2], [0.0, 0.0, 1.0]]))


def test_assignment_is_optimal_and_never_uses_stuff_slot():
    cost = -np.array([[0.9, 0.8, 0.1, 0.1], [0.9, 0.7, 0.6, 0.0]])
    assert assign(cost).tolist() == [1, 2]


def test_equal_costs_and_more_segments_than_slots_stay_finite():
    out = assign(np.zeros((5, 3)))
    assert set(out) <= {1, 2} and len(out) == 5
    out = assign(np.full((2, 4), np.nan))
    assert sorted(out) != [] and np.all(out >= 1)


def test_window_segments_one_frustum_apart_never_share_slots():
    w = SlotWindow.for_scene(max_fruits_per_frustum=6, frustum_length_m=0.5, n_slots=41, margin=2)
    for s in np.linspace(0, 3, 31):
        a, b = w.allowed(np.array([s, s + 0.5]))
        assert a.sum() == w.width and b.sum() == w.width
        assert not (a & b).any()
        assert not a[0] and not b[0]


def test_window_forces_different_slots_for_far_apart_fruits():
    # Two segments that both prefer slot 1 strongly, one frustum length apart.
    w = SlotWindow.for_scene(4, 1.0, 17, margin=0)
    cost = np.full((2, 17), -0.01)
    cost[:, 1] = -0.99
    allowed = w.allowed(np.array([0.0, 1.0]))
    plain = assign(cost[:1]), assign(cost[1:])
    assert plain[0][0] == plain[1][0] == 1          # without the window: the repeated ID
    a0, a1 = assign(cost[:1], allowed[:1])[0], assign(cost[1:], allowed[1:])[0]
    assert allowed[0, a0] and allowed[1, a1] and a0 != a1


def test_too_few_slots_is_a_clear_error():
    with pytest.raises(ValueError, match="too few for repeated-ID rejection"):
        SlotWindow.for_scene(10, 0.5, 16)


def test_outside_cost_is_finite_and_dominates():
    assert np.isfinite(OUTSIDE_COST) and OUTSIDE_COST > 1


def test_along_track_follows_the_trajectory_direction():
    cams = np.stack([np.linspace(0, 1, 5), np.zeros(5), np.zeros(5)], 1)[::-1] + [0, 0.6, 0]
    s = along_track(np.array([[1.0, 0.0, 0.2], [0.5, 1.0, 0.0]]), cams)
    assert s == pytest.approx([0.0, 0.5])


def test_position_preference_makes_untrained_assignments_agree_between_frames():
    win = SlotWindow.for_scene(max_fruits_per_frustum=4, frustum_length_m=0.4, n_slots=33)
    uniform = -np.full((3, 33), 1 / 33)
    # the same three fruits (positions along the row) seen in two frames, listed in different orders
    along_a = np.array([0.10, 0.22, 0.31])
    order = np.array([2, 0, 1])
    slots = []
    for along in (along_a, along_a[order]):
        cost = uniform + 0.05 * position_preference(win, along)
        slots.append(assign(cost, win.allowed(along)))
    assert np.array_equal(slots[0][order], slots[1])          # each fruit got the same slot in both frames
    assert len(set(slots[0])) == 3 and 0 not in slots[0]
    pref = position_preference(win, along_a)
    assert pref.shape == (3, 33) and (pref[:, 0] == 1).all() and (pref >= 0).all() and (pref <= 1).all()


def test_slot_memory_gives_a_fruit_its_slot_again_and_new_fruits_free_slots():
    from nerf.panoptic.assignment import SlotMemory, segment_geometry

    mem = SlotMemory(6)
    a, b = np.array([0.0, 0.0, 0.7]), np.array([0.0, 0.08, 0.7])   # two fruits stacked 8 cm apart
    mem.update(np.array([2, 4]), np.stack([a, b]))
    # the same two fruits in another frame, listed the other way round, with equal (untrained) probabilities
    cost = -np.full((2, 6), 1 / 6) + 0.3 * mem.cost(np.stack([b + 0.005, a - 0.005]), np.array([0.05, 0.05]))
    assert assign(cost).tolist() == [4, 2]
    # a fruit 30 cm away is another fruit: it prefers a slot nobody took over both remembered ones
    c = mem.cost(np.array([[0.3, 0.0, 0.7]]), np.array([0.05]))
    assert c[0, 2] == c[0, 4] == 1.0 and c[0, 1] == SlotMemory.UNSEEN and c[0, 0] == 1.0
    assert assign(-np.full((1, 6), 1 / 6) + 0.3 * c)[0] not in (2, 4)
    # a non-finite centre does not move the memory
    mem.update(np.array([2]), np.array([[np.nan, 0.0, 0.0]]))
    assert np.allclose(mem.centre[2], a)
    pts = np.array([[0, 0, 1], [0.02, 0, 1], [-0.02, 0, 1], [5, 5, 5], [1, 1, 1.0]])
    centres, sizes = segment_geometry(pts, np.array([0, 0, 0, 0, 1]), 2)
    assert np.allclose(centres[0], [0.01, 0, 1]) and sizes[0] > 0 and sizes[1] == pytest.approx(1e-3)
