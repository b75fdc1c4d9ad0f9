"""Fit one NeRF per window (Dask, one task per window) with online pose refinement; render validation frames."""
from __future__ import annotations

import hashlib
import json
import os
import pickle
import shutil
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Literal

import numpy as np
import pandas as pd

import schemas
from nerf.config import NerfConfig, NerfOverrides, PanopticConfig, preset, set_fields
from nerf.depth_poses import DepthPoses
from nerf.geometry import pose_txyzq, rotation_angle_deg
from nerf.memory import release_freed
from pipeline import io, parallel, progress, resources
from pipeline.stage import StageContext
from rowmap import renders as render_files
from rowmap.window_data import initial_poses, load_labels, load_window, window_detections

INPUTS = ("frames", "windows", "detections_filtered")
OUTPUTS = ("window_poses", "window_metrics", "nerf", "renders")
OPTIONAL_INPUTS = ("colmap_poses",)  # initial poses when pose_source = colmap


@dataclass(frozen=True)
class Config:
    preset: Literal["cpu", "S", "L"] = "cpu"
    """model preset (nerf/config.py): cpu for the default run, S and L as in the paper."""
    model: NerfOverrides = field(default_factory=NerfOverrides)
    """overrides of the preset's model and training settings (every NerfConfig setting but preset,
    refine_poses and seed, which are this stage's own; unset = the preset's value)."""
    refine_poses: bool = True
    """optimise the camera poses online (off = keep the initial poses fixed)."""
    pose_source: Literal["odometry", "colmap"] = "odometry"
    """initial poses: 'odometry' (frames.parquet) or 'colmap' (colmap_poses.parquet, needs
    colmap_poses.enabled=true; frames COLMAP could not register keep their odometry pose)."""
    depth_poses: DepthPoses = "icp"
    """correct each window's initial poses with its depth frames before the fit (nerf/depth_poses.py): 'icp'
    = the shape of the trajectory from point-to-plane ICP between consecutive frames, placed onto the
    odometry (a link ICP cannot lock onto keeps the odometry's); 'scale' = only the odometry's scale along
    the window; 'off' = the odometry (or COLMAP) poses as they are. Pose refinement from colour keeps the
    scale and drift it starts from, so keep 'icp' unless the depth is unusable (then 'scale' or 'off');
    'scale' is bit-for-bit reproducible across processes, ICP only to floating-point noise."""
    icp_max_depth_m: float = 0.0
    """depth limit of the ICP pose correction, metres (>= 0; 0 = derived from each window's depth: 2.5 x the 5th
    percentile of its valid depth, rounded up to 0.5 m, nerf/depth_poses.py icp_depth_limit_m). ICP's voxel and
    inlier distance grow with it. Set it only where the derived limit keeps too few or too noisy points."""
    workers: int = 0
    """Dask workers for a local cluster (0 = one per core on the CPU, one per GPU on 'cuda'; at most one per
    window)."""
    threads_per_worker: int = 0
    """torch threads per worker (0 = cores / workers; then, once fewer windows are left than workers, the last
    windows also take the idle workers' cores, and fits reproduce to floating-point noise, not bit for bit)."""
    max_windows: int = 0
    """fit at most this many windows (0 = all)."""
    seed: int = 0
    """random seed of the fits."""
    panoptic: PanopticConfig = field(default_factory=PanopticConfig)
    """the panoptic phase after the colour phase (nerf/panoptic/train.py)."""
    render_scale: float = 0.0
    """working scale of the validation renders that fusion and counting use, in [0, 1]: 0.5 renders them at half width
    and height (intrinsics scaled alike; about a quarter of the render time) and stores them resized back to full size
    (colour bilinear; depth and labels nearest, so no depth or label is invented between two surfaces); labelled frames
    too (docs/benchmarks.md: at full size they cost 4-16x and scored no better). 1 = full size (no resizing); 0 =
    automatic: the largest scale whose renders are at most RENDER_WIDTH (320, nerf/render_scale.py) pixels wide (1 up to
    320x180, 0.5 at 640x360, 0.25 at 1280x720): a window renders every windows.val_every-th frame of its span.
    Validation PSNR is measured at the scale each frame was rendered at (the recorded image area-averaged to that
    size)."""

    def __post_init__(self) -> None:
        if not self.icp_max_depth_m >= 0:
            raise ValueError(f"nerf_fit.icp_max_depth_m must be >= 0 metres (0 = derived), got {self.icp_max_depth_m}")
        if not 0 <= self.render_scale <= 1:
            raise ValueError(f"nerf_fit.render_scale must be in [0, 1] (0 = automatic), got {self.render_scale}")


def model_config(cfg: Config) -> NerfConfig:
    """The preset, with the settings cfg.model sets, and this stage's refine_poses and seed."""
    return preset(cfg.preset, refine_poses=cfg.refine_poses, seed=cfg.seed, **set_fields(cfg.model))


def window_payload(wid: int, w: pd.DataFrame, cfg: Config, mcfg: NerfConfig, device: str, out_dir: Path,
                   data_root: Path, detections: dict | None) -> dict:
    """The task fit_one runs for window `wid` (its frame rows `w` with their initial poses)."""
    return {"window_id": wid, "frames": w.to_dict("list"), "cfg": replace(mcfg, seed=cfg.seed + wid), "device": device,
            "out_dir": str(Path(out_dir).resolve()), "data_root": str(Path(data_root).resolve()),
            "panoptic": cfg.panoptic, "depth_poses": cfg.depth_poses, "detections": detections,
            "render_scale": cfg.render_scale, "icp_max_depth_m": cfg.icp_max_depth_m}


def fit_one(payload: dict) -> dict:
    """Runs in a Dask worker: load the window, fit it (nerf/fit.py), write checkpoint and renders, return rows."""
    frames, data, measured = _start(payload)
    return _finish(payload, frames, data, None, measured)


def fit_colour_part(payload: dict) -> dict:
    """The first part of fit_one as a task of its own: the window's colour phase, written to a scratch file
    in the output folder; returns the payload for fit_rest_part."""
    from nerf.fit import fit_colour, save_colour

    _, data, measured = _start(payload)
    wid = payload["window_id"]
    colour = fit_colour(data, payload["cfg"], payload["depth_poses"], payload["device"], _progress(wid),
                        f"window {wid}", payload["icp_max_depth_m"])
    path = Path(payload["out_dir"]) / COLOUR_SCRATCH / f"window_{wid:03d}.pt"
    path.parent.mkdir(parents=True, exist_ok=True)
    save_colour(colour, path)
    return {**payload, "colour_path": str(path), "colour_peak_mb": resources.own_peak_mb() if measured else np.nan}


def fit_rest_part(payload: dict) -> dict:
    """The second part of fit_one as a task of its own: the rest of the window's fit from the colour phase
    fit_colour_part wrote (whose file it removes), its checkpoint, renders and rows."""
    from nerf.fit import load_colour

    frames, data, measured = _start(payload)
    path = Path(payload["colour_path"])
    colour = load_colour(path, data, payload["device"])
    path.unlink()
    return _finish(payload, frames, data, colour, measured)


COLOUR_SCRATCH = ".colour_phases"
"""Folder in the nerf output where fit_colour_part leaves each window's colour phase for fit_rest_part."""


def _progress(wid: int):
    """progress(done, total, info) of window `wid`'s fit, reported from inside its worker."""
    return lambda s, n, info: parallel.report(str(wid), s, n, **info)


def _start(payload: dict):
    """A task's start: the worker's freed heap handed back, its peak memory reset; the window's frame rows and
    frames loaded. Returns (rows, WindowData, whether the peak is measured)."""
    release_freed()  # a worker fits window after window: the last one's freed heap is not carried into this one
    measured = resources.reset_own_peak()
    frames = pd.DataFrame(payload["frames"])
    _progress(payload["window_id"])(0, len(frames), {"phase": "load frames"})
    return frames, load_window(frames, Path(payload["data_root"])), measured


def _finish(payload: dict, frames: pd.DataFrame, data, colour, measured: bool) -> dict:
    """The window's fit from its colour phase (None: fitted here too), then its checkpoint, renders and rows."""
    import torch

    from nerf.fit import fit_panoptic_window

    wid, out_dir, data_root = payload["window_id"], Path(payload["out_dir"]), Path(payload["data_root"])
    detections = pd.DataFrame(payload["detections"]) if payload["detections"] else None
    fit = fit_panoptic_window(data, lambda: load_labels(frames, detections, data_root), payload["cfg"],
                              payload["panoptic"], depth_poses=payload["depth_poses"],
                              render_scale=payload["render_scale"], device=payload["device"],
                              progress=_progress(wid), name=f"window {wid}",
                              icp_max_depth_m=payload["icp_max_depth_m"], colour=colour, keep_colour=False)
    res, pan = fit.colour, fit.panoptic
    name = f"window_{wid:03d}"
    resume = Path(payload["resume_dir"]) if payload.get("resume_dir") else None
    # with a resume folder the window is built under a temp name there and renamed into place when complete
    # (inside a temp folder whose name the run's leftover cleanup knows); the renders' table rows name the
    # files relative to the nerf folder either way
    wdir = resume / f".{name}.tmp-{os.getpid()}" / name if resume else out_dir / name
    if resume:
        shutil.rmtree(wdir.parent, ignore_errors=True)
    (wdir / "renders").mkdir(parents=True, exist_ok=True)
    state = res.model.state()
    if pan is not None:
        state["panoptic"] = pan.state()
    torch.save(state, wdir / "checkpoint.pt")
    kinds = render_files.KINDS if pan is not None else ("rgb", "depth")
    render_rows = []
    for i in np.flatnonzero(~data.is_train):
        out = res.renders[int(i)]
        render_rows += render_files.write_frame(wdir.parent, wid, int(data.frame_ids[i]), {k: out[k] for k in kinds})
    init = data.poses_c2w  # the odometry (or COLMAP) poses, before the depth correction
    final = res.poses_c2w
    dt = np.linalg.norm(final[:, :3, 3] - init[:, :3, 3], axis=1)
    drot = rotation_angle_deg(init[:, :3, :3], final[:, :3, :3])
    q = pose_txyzq(final)
    poses = pd.DataFrame({"window_id": wid, "frame_id": data.frame_ids.astype(np.int32),
                          "split": np.where(data.is_train, "train", "val"),
                          "source": frames["pose_source"].to_numpy() if "pose_source" in frames else "odometry",
                          "refined": bool(payload["cfg"].refine_poses),
                          **{c: q[:, j] for j, c in enumerate(["tx", "ty", "tz", "qx", "qy", "qz", "qw"])},
                          "delta_t_m": dt, "delta_rot_deg": drot})
    metrics = {"window_id": wid, "status": "ok", "error": "", "params": res.params, "steps": res.steps,
               "fit_s": res.fit_s, "render_s_per_image": res.render_s_per_image,
               "samples_per_ray": res.samples_per_ray,
               "val_psnr": float(np.mean(list(res.val_psnr.values()))) if res.val_psnr else float("nan"),
               "train_psnr": res.train_psnr, "threads": torch.get_num_threads(),
               "peak_rss_mb": float(np.fmax(resources.own_peak_mb() if measured else np.nan,   # over both parts
                                            payload.get("colour_peak_mb", np.nan))),
               "panoptic_steps": pan.steps if pan else 0, "panoptic_fit_s": pan.fit_s if pan else 0.0,
               "panoptic_params": pan.params if pan else 0,
               "panoptic_instances": bool(pan is not None and pan.cfg.instances), "n_slots": pan.n_slots if pan else 0,
               "id_window_width": pan.slot_window.width if pan and pan.slot_window else 0,
               **fit.depth_info, "far_m": float(res.model.cfg.far_m), "pose_shift_weight": res.shift_weight,
               "checkpoint": f"window_{wid:03d}/checkpoint.pt"}
    result = {"poses": poses.to_dict("list"), "metrics": metrics, "renders": render_rows}
    if resume:
        with open(wdir / FINISHED, "wb") as fh:
            pickle.dump({"digest": payload["digest"], "result": result}, fh)
        io.fsync_tree(wdir)
        shutil.rmtree(resume / name, ignore_errors=True)
        os.replace(wdir, resume / name)  # the window is complete once it has its final name
        io.fsync_dir(resume)
        shutil.rmtree(wdir.parent, ignore_errors=True)
    return result


FINISHED = "finished.pkl"
"""In a finished window's resume folder: the payload digest and the window's table rows."""


def payload_digest(payload: dict) -> str:
    """Hash of what a window's fit depends on (its frames, initial poses, detections and settings)."""
    keep = {k: v for k, v in payload.items() if k not in ("out_dir", "resume_dir", "digest")}
    text = json.dumps(keep, sort_keys=True, default=repr)
    return hashlib.blake2b(text.encode(), digest_size=16).hexdigest()


def finished_window(folder: Path, digest: str) -> dict | None:
    """The table rows of a window an earlier (interrupted) run finished in `folder`, or None."""
    marker = folder / FINISHED
    if not marker.is_file():
        return None
    try:
        with open(marker, "rb") as fh:
            done = pickle.load(fh)
    except (OSError, EOFError, pickle.UnpicklingError, AttributeError, ImportError):
        return None
    return done["result"] if isinstance(done, dict) and done.get("digest") == digest else None


def link_tree(src: Path, dst: Path, skip: tuple[str, ...] = ()) -> None:
    """Hard-link (or copy, across file systems) every file of `src` into `dst`."""
    for p in sorted(src.rglob("*")):
        if p.is_dir() or p.name in skip:
            continue
        target = dst / p.relative_to(src)
        target.parent.mkdir(parents=True, exist_ok=True)
        try:
            os.link(p, target)
        except OSError:
            shutil.copy2(p, target)


def run(inputs: dict, cfg: Config, ctx: StageContext) -> dict[str, pd.DataFrame]:
    frames: pd.DataFrame = inputs["frames"]
    windows: pd.DataFrame = inputs["windows"]
    wids = sorted(windows["window_id"].unique())
    if cfg.max_windows:
        wids = wids[: cfg.max_windows]
    if not wids:
        raise ValueError("nerf_fit: the windows table is empty")
    mcfg = model_config(cfg)
    out_dir = ctx.output_dir("nerf")
    payloads = {}
    colmap = inputs.get("colmap_poses")
    dets = inputs.get("detections_filtered")
    for i, wid in enumerate(wids):
        w = windows[windows.window_id == wid].merge(frames, on="frame_id", how="left")
        if w["rgb_path"].isna().any():
            raise ValueError(f"window {wid}: frames {w.loc[w.rgb_path.isna(), 'frame_id'].tolist()} not in frames.parquet")
        w = initial_poses(w, int(wid), colmap, cfg.pose_source)
        device = parallel.spread_over_gpus(ctx.device, i)
        payloads[str(wid)] = window_payload(int(wid), w, cfg, mcfg, device, out_dir, ctx.data_root,
                                            window_detections(dets, w))
    # workers and threads follow the whole row, also when some windows are reused: a window's fit is then
    # computed with the same thread count as in an uninterrupted run
    n_workers = cfg.workers or parallel.default_workers(len(payloads), ctx.device)
    threads = parallel.task_threads(cfg.threads_per_worker, n_workers)
    resume = ctx.resume_dir.resolve() if ctx.resume_dir is not None else None
    outcomes: dict[str, parallel.TaskOutcome] = {}
    if resume is not None:
        resume.mkdir(parents=True, exist_ok=True)
        for key, p in payloads.items():
            p["digest"], p["resume_dir"] = payload_digest(p), str(resume)
            done = finished_window(resume / f"window_{int(key):03d}", p["digest"])
            if done is not None:
                outcomes[key] = parallel.TaskOutcome(key, result=done)
                ctx.count("windows_reused")
                if ctx.show_progress:
                    progress.say(f"nerf_fit window {key}: reused (finished by an interrupted run of the same "
                                 f"code, config and inputs)")
    todo = {k: p for k, p in payloads.items() if k not in outcomes}
    if todo:
        # on a cluster of the stage's own where the last round of windows would leave a worker idle (3 windows
        # on 2 workers): each window's colour phase and the rest of its fit are two tasks, every colour phase
        # first, so the last window's colour phase runs beside the others' panoptic phases, not alone
        split = parallel.own_cluster(ctx.scheduler) and len(todo) > n_workers > 1 and len(todo) % n_workers > 0
        try:
            outcomes.update(parallel.map_tasks(fit_colour_part if split else fit_one, todo,
                                               n_workers=min(n_workers, len(todo)), threads_per_worker=threads,
                                               scheduler=ctx.scheduler, show_progress=ctx.show_progress,
                                               desc="window", label="nerf_fit window",
                                               progress_interval_s=ctx.progress_interval_s,
                                               idle_threads=cfg.threads_per_worker == 0,
                                               then=fit_rest_part if split else None))
        finally:
            shutil.rmtree(out_dir / COLOUR_SCRATCH, ignore_errors=True)
    pose_tables, metric_rows, render_rows = [], [], []
    for key in payloads:
        o = outcomes[key]
        if resume is not None and o.error is None:
            name = f"window_{int(key):03d}"
            link_tree(resume / name, out_dir / name, skip=(FINISHED,))
        wid = int(key)
        centre = int(windows.loc[windows.window_id == wid, "center_frame_id"].iloc[0])
        w = windows[windows.window_id == wid]
        base = {"window_id": wid, "center_frame_id": centre, "preset": mcfg.preset, "device": payloads[key]["device"],
                "n_train": int((w.split == "train").sum()), "n_val": int((w.split == "val").sum()),
                "worker": o.worker}
        if o.error is not None:
            msg = str(o.error).splitlines()[0] if str(o.error) else type(o.error).__name__
            ctx.note(f"window {wid} failed: {msg}")
            ctx.count("windows_failed")
            metric_rows.append({**base, "status": "failed", "error": msg, "threads": threads, "params": 0, "steps": 0,
                                "fit_s": o.seconds, "render_s_per_image": np.nan, "samples_per_ray": np.nan,
                                "val_psnr": np.nan, "train_psnr": np.nan, "checkpoint_path": "",
                                "panoptic_steps": 0, "panoptic_fit_s": 0.0, "panoptic_params": 0,
                                "panoptic_instances": False, "n_slots": 0,
                                "id_window_width": 0, "depth_poses": cfg.depth_poses, "odometry_scale": np.nan,
                                "depth_pose_votes": 0, "depth_pose_note": "", "icp_max_depth_m": np.nan,
                                "far_m": np.nan, "pose_shift_weight": np.nan, "peak_rss_mb": np.nan})
            continue
        m = dict(o.result["metrics"])
        m["checkpoint_path"] = ctx.relpath("nerf", m.pop("checkpoint"))
        metric_rows.append({**base, **m})
        pose_tables.append(pd.DataFrame(o.result["poses"]))
        render_rows += [{"window_id": r["window_id"], "frame_id": r["frame_id"], "kind": r["kind"],
                         "path": ctx.relpath("nerf", r["file"])} for r in o.result["renders"]]
    metrics = pd.DataFrame(metric_rows)
    poses = pd.concat(pose_tables, ignore_index=True) if pose_tables else None
    if poses is None:
        raise RuntimeError("nerf_fit: every window failed: " + "; ".join(metrics["error"]))
    ok = metrics[metrics.status == "ok"]
    ctx.summary.update(windows=len(metrics), failed=int((metrics.status != "ok").sum()),
                       mean_val_psnr=round(float(ok.val_psnr.mean()), 2), mean_fit_s=round(float(ok.fit_s.mean()), 1))
    renders = pd.DataFrame(render_rows, columns=schemas.get("renders").names) if render_rows else schemas.empty("renders")
    return {"window_poses": poses, "window_metrics": metrics, "renders": renders}
