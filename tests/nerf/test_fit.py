"""The one fitting sequence of a window (nerf/fit.py): depth poses, colour phase, panoptic phase, validation
renders, instance completion; one colour phase shared by several panoptic variants; errors naming the window."""
import numpy as np
import pytest
import torch

from nerf import fit as fitmod
from nerf.config import PanopticConfig, preset
from nerf.fit import fit_colour, fit_panoptic_window, load_colour, save_colour
from nerf.panoptic.labels import WindowLabels
from nerf.trainer import NonFiniteLoss

COLOUR = dict(steps=10, rays_per_step=128, n_levels=4, log2_capacity=12, occupancy_res=32, occupancy_every=1000,
              pose_warmup_steps=5, val_register_every=5, val_register_steps=1, val_register_final_steps=2)
PANOPTIC = PanopticConfig(steps=4, rays_per_frame=32, frames_per_step=2)


@pytest.fixture(scope="module")
def window_and_labels(labelled_window):
    data, sem, inst = labelled_window
    return data, WindowLabels(sem, inst)


def test_labels_are_loaded_after_the_colour_phase_and_every_validation_frame_is_rendered(window_and_labels):
    data, labels = window_and_labels
    before = data.poses_c2w.copy()
    events = []

    def load():
        events.append("labels loaded")
        return labels

    fit = fit_panoptic_window(data, load, preset("cpu", **COLOUR), PANOPTIC, render_scale=0.5,
                              progress=lambda s, n, info: events.append(info.get("phase", "colour step")))
    val = np.flatnonzero(~data.is_train)
    assert sorted(fit.colour.renders) == val.tolist()
    assert sorted(fit.colour.val_psnr) == data.frame_ids[val].tolist()
    assert all(fit.colour.renders[int(i)]["instance"].shape == (24, 40) for i in val)   # stored at full size
    assert fit.panoptic is not None and fit.depth_info["depth_poses"] == "off"
    first = {e: events.index(e) for e in reversed(events)}
    last = {e: len(events) - 1 - events[::-1].index(e) for e in events}
    assert last["depth poses"] < first["colour step"] and last["colour step"] < first["labels loaded"]
    assert first["labels loaded"] < first["panoptic step"] and last["panoptic step"] < first["panoptic validation render"]
    assert events[-1] == "instance completion" and events.count("labels loaded") == 1
    np.testing.assert_array_equal(data.poses_c2w, before)   # the caller's window is not changed


def test_without_the_panoptic_phase_no_labels_are_loaded(window_and_labels):
    data, _ = window_and_labels
    phases = []

    def load():
        raise AssertionError("labels loaded with the panoptic phase off")

    fit = fit_panoptic_window(data, load, preset("cpu", **COLOUR), PanopticConfig(enabled=False),
                              progress=lambda s, n, info: phases.append(info.get("phase")))
    assert fit.panoptic is None and "validation render" in phases
    assert set(fit.colour.renders[0]) >= {"rgb", "depth"} and "semantic" not in fit.colour.renders[0]


def test_the_colour_phase_starts_from_the_depth_corrected_poses(window_and_labels, monkeypatch):
    data, _ = window_and_labels
    calls = []

    def corrected(mode, depths, intrinsics, c2w, max_depth_m=0.0):
        calls.append(mode)
        out = c2w.copy()
        out[:, 0, 3] += 0.01
        return out, {"depth_poses": mode, "odometry_scale": 1.0, "depth_pose_votes": 3, "depth_pose_note": ""}

    monkeypatch.setattr(fitmod, "depth_initial_poses", corrected)
    fit = fit_panoptic_window(data, None, preset("cpu", **COLOUR, refine_poses=False), PanopticConfig(enabled=False),
                              depth_poses="icp")
    assert calls == ["icp"] and fit.depth_info["depth_pose_votes"] == 3
    np.testing.assert_allclose(fit.initial_poses[:, 0, 3], data.poses_c2w[:, 0, 3] + 0.01)
    np.testing.assert_allclose(fit.colour.poses_c2w, fit.initial_poses, atol=1e-6)   # fixed poses: kept


@pytest.fixture
def one_thread():
    """One torch thread: threaded sums add in varying order, so two equal fits differ by float noise."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def test_a_shared_colour_phase_gives_a_variant_the_fit_it_would_get_alone(window_and_labels, one_thread):
    data, labels = window_and_labels
    cfg = preset("cpu", **COLOUR)
    shared_grid = PanopticConfig(steps=4, rays_per_frame=32, frames_per_step=2, grid_mode="shared")
    alone = fit_panoptic_window(data, labels, cfg, shared_grid)
    colour = fit_colour(data, cfg)
    grid = [p.detach().clone() for p in colour.result.model.field.parameters()]
    reused = fit_panoptic_window(data, labels, cfg, shared_grid, colour=colour)
    for i, r in alone.colour.renders.items():
        np.testing.assert_array_equal(reused.colour.renders[i]["instance"], r["instance"])
        np.testing.assert_array_equal(reused.colour.renders[i]["semantic"], r["semantic"])
        assert torch.equal(reused.colour.renders[i]["rgb"], r["rgb"])
    # the 'shared' panoptic phase trains the colour grid: on a copy, so the next variant starts from the same
    assert all(torch.equal(a, b) for a, b in zip(grid, colour.result.model.field.parameters()))
    assert not all(torch.equal(a, b) for a, b in zip(grid, reused.colour.model.field.parameters()))
    assert colour.result.renders == {}
    with pytest.raises(ValueError, match="other settings"):
        fit_panoptic_window(data, labels, preset("cpu", **COLOUR, seed=1), shared_grid, colour=colour)


def test_a_colour_phase_saved_and_loaded_in_another_process_fits_the_same_window(window_and_labels, one_thread,
                                                                                tmp_path):
    data, labels = window_and_labels
    cfg = preset("cpu", **COLOUR)
    colour = fit_colour(data, cfg, depth_poses="scale")
    in_memory = fit_panoptic_window(data, labels, cfg, PANOPTIC, depth_poses="scale", colour=colour)
    save_colour(colour, tmp_path / "colour.pt")
    loaded = load_colour(tmp_path / "colour.pt", data)   # the window as a new process loads it again
    assert loaded.depth_info == colour.depth_info and loaded.result.steps == colour.result.steps
    np.testing.assert_array_equal(loaded.data.poses_c2w, colour.data.poses_c2w)   # the depth-corrected poses
    again = fit_panoptic_window(data, labels, cfg, PANOPTIC, depth_poses="scale", colour=loaded)
    twice = fit_panoptic_window(data, labels, cfg, PANOPTIC, depth_poses="scale", colour=colour)
    for other in (again, twice):   # the heads start from the colour phase's random state, not what ran since
        assert in_memory.colour.val_psnr == other.colour.val_psnr
        for i, r in in_memory.colour.renders.items():
            np.testing.assert_array_equal(other.colour.renders[i]["instance"], r["instance"])
            assert torch.equal(other.colour.renders[i]["rgb"], r["rgb"])
    np.testing.assert_array_equal(again.initial_poses, in_memory.initial_poses)
    handed_over = fit_panoptic_window(data, labels, cfg, PANOPTIC, depth_poses="scale", colour=loaded,
                                      keep_colour=False)   # as nerf_fit's second part: no copy of the model
    assert handed_over.colour is loaded.result and handed_over.colour.renders
    assert in_memory.colour.val_psnr == handed_over.colour.val_psnr
    with pytest.raises(ValueError, match="a colour phase of"):
        load_colour(tmp_path / "colour.pt", data.take(np.arange(3)))


def test_a_failing_phase_names_the_window(window_and_labels, monkeypatch):
    data, labels = window_and_labels
    cfg = preset("cpu", **COLOUR)
    colour = fit_colour(data, cfg)
    small = WindowLabels(labels.semantic[:, :12], labels.instance[:, :12], labels.scores)
    with pytest.raises(RuntimeError, match=r"window 7 \(panoptic phase\): labels are 40x12"):
        fit_panoptic_window(data, small, cfg, PANOPTIC, colour=colour, name="window 7")

    def diverges(*args, **kwargs):
        raise NonFiniteLoss("non-finite loss (nan) at step 3")

    monkeypatch.setattr(fitmod, "fit_window", diverges)
    with pytest.raises(RuntimeError, match="^window 7: non-finite loss"):
        fit_colour(data, cfg, name="window 7")
