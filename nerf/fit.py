"""Fit one window end to end: its initial poses corrected with depth, the colour phase, the panoptic phase,
the validation renders (at a working scale) and the 3D instance completion.

`fit_panoptic_window` is the one fitting sequence: the nerf_fit stage and the benchmarks that fit windows
(bench/ablation.py, bench/compare.py) all call it, so what they report is what the pipeline fits.
"""
from __future__ import annotations

import copy
import time
from collections.abc import Callable
from dataclasses import dataclass, fields, replace
from pathlib import Path

import numpy as np
import torch

from nerf.config import NerfConfig, PanopticConfig
from nerf.depth_poses import DepthPoses, depth_initial_poses
from nerf.memory import release_freed
from nerf.model import NerfModel
from nerf.panoptic.complete import complete_instances
from nerf.panoptic.labels import WindowLabels
from nerf.panoptic.render import render_panoptic
from nerf.panoptic.result import PanopticResult
from nerf.panoptic.train import fit_panoptic
from nerf.render_scale import render_at, working_scale
from nerf.trainer import FitResult, fit_window, validate
from nerf.window import WindowData

Progress = Callable[[int, int, dict], None]
"""progress(done, total, info): info['phase'] names the work ('depth poses', 'panoptic step', 'validation
render', 'panoptic validation render', 'instance completion'); the colour phase's steps carry {'psnr': dB}
and no phase."""


@dataclass
class ColourPhase:
    """A window's colour phase: the depth-corrected initial poses and the fitted colour model (no renders)."""

    cfg: NerfConfig
    depth_poses: DepthPoses
    data: WindowData
    """the window as fitted: its poses_c2w are the depth-corrected initial poses."""
    result: FitResult
    depth_info: dict
    """what depth_initial_poses did: depth_poses, odometry_scale, depth_pose_votes, depth_pose_note,
    icp_max_depth_m."""
    rng_state: torch.Tensor
    """torch's random state when the colour phase ended: the panoptic phase starts from it (its heads' first
    weights), in this process or another, and so does every variant that reuses the colour phase."""


@dataclass
class WindowFit:
    """A fitted window: colour model with its final poses and validation renders, and the panoptic part."""

    colour: FitResult
    """model, final poses [N, 4, 4], and the validation frames' renders (window frame index -> render dict:
    rgb (uint8), depth, with the panoptic phase also semantic and instance) with their PSNR and timing."""
    panoptic: PanopticResult | None
    """the panoptic part (None with the panoptic phase off)."""
    initial_poses: np.ndarray
    """[N, 4, 4] the poses the colour phase started from (the window's poses corrected with depth)."""
    depth_info: dict
    """what depth_initial_poses did: depth_poses, odometry_scale, depth_pose_votes, depth_pose_note,
    icp_max_depth_m."""


def fit_colour(data: WindowData, cfg: NerfConfig, depth_poses: DepthPoses = "off", device: str = "cpu",
               progress: Progress | None = None, name: str = "window", icp_max_depth_m: float = 0.0) -> ColourPhase:
    """The colour phase of fit_panoptic_window: the window's initial poses corrected with its depth frames
    (nerf/depth_poses.py, `depth_poses`), then the colour fit from them (nerf/trainer.py, without renders).
    `data` is not changed."""
    report = progress or _silent
    report(0, 1, {"phase": "depth poses"})
    poses, depth_info = depth_initial_poses(depth_poses, data.depths, data.intrinsics, data.poses_c2w,
                                            max_depth_m=icp_max_depth_m)
    report(1, 1, {"phase": "depth poses"})
    release_freed()  # ICP's point clouds (C++ heap) are not held through the colour fit
    fitted = copy.copy(data)
    fitted.poses_c2w = poses
    try:
        res = fit_window(fitted, cfg, device=device, render_val=False, progress=progress)
    except Exception as err:
        raise RuntimeError(f"{name}: {err}") from err
    return ColourPhase(cfg, depth_poses, fitted, res, depth_info, torch.get_rng_state())


def save_colour(colour: ColourPhase, path: Path) -> None:
    """Write a colour phase to `path` without the window's images and depth (load_colour takes them again):
    the model's checkpoint state, the depth-corrected poses and the fit's record."""
    record = {f.name: getattr(colour.result, f.name) for f in fields(colour.result)
              if f.name not in ("model", "renders")}
    torch.save({"cfg": colour.cfg, "depth_poses": colour.depth_poses, "poses_c2w": colour.data.poses_c2w,
                "depth_info": colour.depth_info, "rng_state": colour.rng_state, "model": colour.result.model.state(),
                "result": record}, path)


def load_colour(path: Path, data: WindowData, device: str = "cpu") -> ColourPhase:
    """The colour phase save_colour wrote for window `data` (the window as loaded, before the depth correction):
    a panoptic phase from it fits as from the colour phase in memory."""
    saved = torch.load(path, map_location=device, weights_only=False)
    if len(saved["poses_c2w"]) != len(data.poses_c2w):
        raise ValueError(f"{path}: a colour phase of {len(saved['poses_c2w'])} frames, the window has "
                         f"{len(data.poses_c2w)}")
    result = FitResult(NerfModel.from_state(saved["model"], device), **saved["result"])
    return ColourPhase(saved["cfg"], saved["depth_poses"], replace(data, poses_c2w=saved["poses_c2w"]), result,
                       saved["depth_info"], saved["rng_state"])


def fit_panoptic_window(data: WindowData, labels: WindowLabels | Callable[[], WindowLabels] | None,
                        cfg: NerfConfig, panoptic: PanopticConfig, depth_poses: DepthPoses = "off",
                        render_scale: float = 1.0, device: str = "cpu",
                        progress: Progress | None = None, colour: ColourPhase | None = None,
                        name: str = "window", icp_max_depth_m: float = 0.0, keep_colour: bool = True) -> WindowFit:
    """Fit window `data` and render its validation frames.

    1. fit_colour: initial poses corrected with depth (`depth_poses`), colour phase with `cfg`;
    2. with panoptic.enabled: the panoptic phase from the detector's `labels` (a WindowLabels, or a function
       that loads them: called only after the colour phase, so a window's label images are not held through
       it), seeded with cfg.seed; then colour and panoptic rendered in one pass per validation frame, at the
       working scale working_scale(render_scale, width) (0 = automatic, 1 = full size), and the 3D instance
       completion over those renders;
       without it: the colour renders of the validation frames, at full size.

    `colour`: the colour phase already fitted by fit_colour(data, cfg, depth_poses); with `keep_colour` the
    panoptic phase trains on a copy of it, so one colour fit serves several panoptic variants (bench/ablation.py);
    without, on it (its renders and model become the fit's: for a caller that uses it once, a model's copy less).
    `name` is how errors of the two fits name the window ('window 3: ...'). Progress goes to
    `progress(done, total, info)` (see Progress)."""
    if colour is None:
        colour = fit_colour(data, cfg, depth_poses, device, progress, name, icp_max_depth_m)
    elif (colour.cfg, colour.depth_poses) != (cfg, depth_poses):
        raise ValueError(f"{name}: the colour phase given was fitted with other settings than cfg and "
                         f"depth_poses={depth_poses!r} (it has depth_poses={colour.depth_poses!r})")
    elif keep_colour:
        colour = copy.copy(colour)
        colour.result = copy.deepcopy(colour.result)  # the panoptic phase may train the colour grid (grid_mode shared)
    fitted, res = colour.data, colour.result
    report = progress or _silent
    release_freed()  # each phase below starts without the last one's freed arrays resident
    pan = None
    if not panoptic.enabled:
        validate(res, fitted, _reporting(res.model.render_image, fitted.is_train, "validation render", progress))
    else:
        window_labels = labels() if callable(labels) else labels
        if window_labels is None:
            raise ValueError(f"{name}: the panoptic phase needs the detector's labels of the window, got None")
        torch.set_rng_state(colour.rng_state)
        try:
            pan = fit_panoptic(res.model, window_labels, fitted.is_train, fitted.depths, panoptic, seed=cfg.seed,
                               progress=lambda s, n, info: report(s, n, {"phase": "panoptic step", **info}))
        except Exception as err:
            raise RuntimeError(f"{name} (panoptic phase): {err}") from err
        del window_labels  # a window's label images are not needed past the fit (hundreds of MB at 1280x720)
        release_freed()
        scale = working_scale(render_scale, res.model.wh[0])
        render = render_at(lambda m, i: render_panoptic(m, pan, i), res.model, scale)
        validate(res, fitted, _reporting(render, fitted.is_train, "panoptic validation render", progress))
        val = [int(i) for i in np.flatnonzero(~fitted.is_train)]
        release_freed()
        report(0, 1, {"phase": "instance completion"})
        complete_instances([res.renders[i] for i in val], fitted.intrinsics[val], res.poses_c2w[val], pan.cfg)
        report(1, 1, {"phase": "instance completion"})
    return WindowFit(res, pan, fitted.poses_c2w, colour.depth_info)


def _silent(done: int, total: int, info: dict) -> None:
    pass


def _reporting(render: Callable[[int], dict], is_train: np.ndarray, what: str, progress: Progress | None
               ) -> Callable[[int], dict]:
    """`render(i)` that reports each finished validation frame (with its seconds) as progress of phase `what`."""
    if progress is None:
        return render
    n = int((~is_train).sum())
    done = [0]

    def wrapped(i: int) -> dict:
        if done[0] == 0:
            progress(0, n, {"phase": what})
        t0 = time.perf_counter()
        out = render(i)
        done[0] += 1
        progress(done[0], n, {"phase": what, "frame_s": round(time.perf_counter() - t0, 2)})
        return out

    return wrapped
