"""Fit one NeRF per window (Dask, one task per window) with online pose refinement; render validation frames."""
from __future__ import annotations

import os
import traceback
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Literal

import numpy as np
import pandas as pd

from nerf.config import NerfConfig, preset
from nerf.depth_poses import DepthPoses, depth_initial_poses
from nerf.panoptic_fit import PanopticConfig
from nerf.geometry import pose_matrix, pose_txyzq, rotation_angle_deg
from pipeline import parallel
from pipeline.classes import VOID
from pipeline.images import read_depth_m, read_label, read_rgb, write_png
from pipeline.stage import StageContext

INPUTS = ("frames", "windows", "detections_filtered")
OUTPUTS = ("window_poses", "window_metrics", "nerf")
OPTIONAL_INPUTS = ("colmap_poses",)  # initial poses when pose_source = colmap


@dataclass(frozen=True)
class ModelOverrides:
    """Optional overrides of the preset's model/training settings (0 or negative = keep the preset's)."""

    steps: int = 0
    """optimisation steps."""
    rays_per_step: int = 0
    """rays per step."""
    n_levels: int = 0
    """levels of the colour grid."""
    log2_capacity: int = 0
    """log2 table size per level."""
    depth_loss_weight: float = -1.0
    """weight of the depth loss."""
    depth_loss_fade: float = -1.0
    """share of the steps over which the depth loss weight falls to 0 (nerf/config.py; 0 = constant weight)."""
    skip_empty: int = -1
    """1 = occupancy skipping, 0 = every sample inside the window's bounds (benchmarks)."""


@dataclass(frozen=True)
class Config:
    preset: Literal["cpu", "S", "L"] = "cpu"
    """model preset (nerf/config.py): cpu for the default run, S and L as in the paper."""
    model: ModelOverrides = field(default_factory=ModelOverrides)
    """per-setting overrides of the preset."""
    refine_poses: bool = True
    """optimise the camera poses online (off = keep the initial poses fixed)."""
    pose_source: Literal["odometry", "colmap"] = "odometry"
    """initial poses: 'odometry' (frames.parquet) or 'colmap' (colmap_poses.parquet, needs
    colmap_poses.enabled=true; frames COLMAP could not register keep their odometry pose)."""
    depth_poses: DepthPoses = "icp"
    """correct each window's initial poses with its depth frames before the fit (nerf/depth_poses.py): 'icp'
    = the shape of the trajectory from point-to-plane ICP between consecutive frames, placed onto the
    odometry (about 3 s per window; a link ICP cannot lock keeps the odometry's); 'scale' = only the
    odometry's scale along the window; 'off' = the odometry (or COLMAP) poses as they are. Pose refinement
    from colour keeps the scale and drift it starts from. Default row, refined ATE (rigid): off 5.1 mm, scale
    2.0 mm, against 6.0 mm for the odometry."""
    workers: int = 0
    """Dask workers for a local cluster (0 = one per core, at most one per window)."""
    threads_per_worker: int = 0
    """torch threads per worker (0 = cores / workers)."""
    max_windows: int = 0
    """fit at most this many windows (0 = all)."""
    seed: int = 0
    """random seed of the fits."""
    panoptic: PanopticConfig = field(default_factory=PanopticConfig)
    """the panoptic phase after the colour phase (nerf/panoptic_fit.py)."""
    render_scale: float = 1.0
    """working scale of the validation renders that fusion and counting use, in (0, 1]: 0.5 renders them at half
    width and height (intrinsics scaled alike; about a quarter of the render time) and stores them resized back
    to full size (colour bilinear; depth and labels nearest, so no depth or label is invented between two
    surfaces). Labelled frames (the window's centre included) are always rendered at full size, so the
    evaluated frames keep their detail. Validation PSNR is measured on the stored images. Lower it for large
    images (1280x720) where full-size renders dominate the cost; 1 = full size (no resizing)."""

    def __post_init__(self) -> None:
        if not 0 < self.render_scale <= 1:
            raise ValueError(f"nerf_fit.render_scale must be in (0, 1], got {self.render_scale}")


def model_config(cfg: Config) -> NerfConfig:
    over = {k: v for k, v in vars(cfg.model).items() if (v >= 0 if k in ("depth_loss_weight", "depth_loss_fade") else v > 0)}
    if "skip_empty" in over or cfg.model.skip_empty == 0:
        over["skip_empty"] = bool(cfg.model.skip_empty)
    return preset(cfg.preset, refine_poses=cfg.refine_poses, seed=cfg.seed, **over)


def load_window(frames: pd.DataFrame, data_root: Path):
    from nerf.trainer import WindowData

    imgs = np.stack([read_rgb(data_root / p) for p in frames["rgb_path"]])
    deps = np.stack([read_depth_m(data_root / p, s) for p, s in zip(frames["depth_path"], frames["depth_scale_m"])])
    k = frames[["fx", "fy", "cx", "cy"]].to_numpy(np.float64)
    poses = pose_matrix(frames[["tx", "ty", "tz", "qx", "qy", "qz", "qw"]].to_numpy(np.float64))
    return WindowData(imgs, deps, k, poses, (frames["split"] == "train").to_numpy(), frames["frame_id"].to_numpy())


def load_labels(frames: pd.DataFrame, dets: pd.DataFrame | None, data_root: Path):
    """The detector's panoptic input of a window's frames (nerf/panoptic_fit.WindowLabels): segments the
    depth filter dropped become void, thing pixels carry their segment's score, stuff pixels 1."""
    from nerf.panoptic_fit import WindowLabels

    sems, insts, confs = [], [], []
    h, w = int(frames["height"].iloc[0]), int(frames["width"].iloc[0])
    for fid, sp, ip in zip(frames["frame_id"], frames["det_semantic_path"], frames["det_instance_path"]):
        if not isinstance(sp, str) or not isinstance(ip, str):  # no detector output for this frame: all void
            sems.append(np.full((h, w), VOID, np.uint8))
            insts.append(np.zeros((h, w), np.int32))
            confs.append(np.zeros((h, w), np.float32))
            continue
        sem = read_label(data_root / sp, "detector semantic").astype(np.uint8)
        inst = read_label(data_root / ip, "detector instance")
        if sem.shape != (h, w) or inst.shape != (h, w):
            raise ValueError(f"frame {fid}: detector PNGs {sp} / {ip} are {sem.shape} / {inst.shape}, "
                             f"the images are {(h, w)}")
        conf = np.where(sem == VOID, 0.0, 1.0).astype(np.float32)
        if dets is not None:
            fd = dets[dets.frame_id == fid]
            lut_keep = np.ones(int(max(inst.max(), fd.segment_id.max() if len(fd) else 0)) + 1, bool)
            lut_score = np.ones(len(lut_keep), np.float32)
            lut_keep[fd.segment_id.to_numpy()] = fd.kept.to_numpy()
            lut_score[fd.segment_id.to_numpy()] = fd.score.to_numpy()
            on = inst > 0
            conf[on] = lut_score[inst[on]]
            drop = on & ~lut_keep[inst]
            sem[drop] = VOID
            inst[drop] = 0
            conf[drop] = 0.0
        sems.append(sem)
        insts.append(inst)
        confs.append(conf)
    return WindowLabels(np.stack(sems), np.stack(insts), np.stack(confs))


def initial_poses(w: pd.DataFrame, wid: int, colmap: pd.DataFrame | None, source: str) -> pd.DataFrame:
    """The window's rows (windows merged with frames) with the initial pose columns taken from `source`
    and a `pose_source` column per frame ('odometry' or 'colmap', as colmap_poses.parquet says)."""
    w = w.copy()
    w["pose_source"] = "odometry"
    if source == "odometry":
        return w
    if colmap is None or colmap.empty:
        raise ValueError("nerf_fit.pose_source=colmap, but colmap_poses.parquet is "
                         f"{'missing' if colmap is None else 'empty'}; run `pag colmap_poses --set "
                         "colmap_poses.enabled=true` first (or `pag all` with that setting)")
    cols = ["tx", "ty", "tz", "qx", "qy", "qz", "qw"]
    c = colmap[colmap.window_id == wid].set_index("frame_id")
    missing = sorted(set(w["frame_id"]) - set(c.index))
    if missing:
        raise ValueError(f"nerf_fit.pose_source=colmap: colmap_poses.parquet has no pose for window {wid}, frames "
                         f"{missing[:10]}; it is older than windows.parquet: rerun `pag colmap_poses`")
    c = c.loc[w["frame_id"]]
    w[cols] = c[cols].to_numpy()
    w["pose_source"] = c["source"].to_numpy()
    return w


def _window_detections(dets: pd.DataFrame | None, w: pd.DataFrame) -> dict | None:
    if dets is None or dets.empty:
        return None
    return dets[dets.frame_id.isin(w.frame_id)][["frame_id", "segment_id", "score", "kept"]].to_dict("list")


def window_payload(wid: int, w: pd.DataFrame, cfg: Config, mcfg: NerfConfig, device: str, out_dir: Path,
                   data_root: Path, detections: dict | None) -> dict:
    """The task fit_one runs for window `wid` (its frame rows `w` with their initial poses)."""
    return {"window_id": wid, "frames": w.to_dict("list"), "cfg": replace(mcfg, seed=cfg.seed + wid), "device": device,
            "out_dir": str(Path(out_dir).resolve()), "data_root": str(Path(data_root).resolve()),
            "panoptic": cfg.panoptic, "depth_poses": cfg.depth_poses, "detections": detections,
            "render_scale": cfg.render_scale}


def scaled_model(model, scale: float):
    """The same model seen through a camera with `scale` times the pixels per side: the image size rounded,
    the intrinsics (fx, fy, cx, cy) scaled by the exact size ratio (pixel centres stay at half-integers, so
    continuous image coordinates simply scale). Shares the field, grid and poses; nothing is copied."""
    w, h = model.wh
    ws, hs = max(1, round(w * scale)), max(1, round(h * scale))
    k = model.intrinsics.clone()
    k[:, 0::2] *= ws / w  # fx, cx
    k[:, 1::2] *= hs / h  # fy, cy
    return replace(model, intrinsics=k, wh=(ws, hs))


def to_full_size(out: dict, wh: tuple[int, int]) -> dict:
    """A render made at a working scale, resized to the image size wh = (W, H): rgb bilinear; depth, opacity
    and labels nearest-neighbour. Tensors stay tensors, arrays stay arrays."""
    import cv2
    import torch

    w, h = wh

    def resize(a, linear: bool):
        is_tensor = isinstance(a, torch.Tensor)
        arr = a.detach().cpu().numpy() if is_tensor else np.asarray(a)
        # cv2 resizes uint8, uint16 and float32; other types (int32 slot ids) go through float32, exact below 2^24
        src = arr if arr.dtype in (np.uint8, np.uint16, np.float32) else arr.astype(np.float32)
        r = cv2.resize(src, (w, h), interpolation=cv2.INTER_LINEAR if linear else cv2.INTER_NEAREST).astype(arr.dtype)
        return torch.from_numpy(r).to(a.device) if is_tensor else r

    res = dict(out)
    for key in ("rgb", "depth", "opacity", "semantic", "instance"):
        if key in out:
            res[key] = resize(out[key], key == "rgb")
    return res


def render_at(render, model, scale: float, full_size: set[int]):
    """render(model, i) -> a render of frame i at the working `scale` (full size for frames in `full_size`),
    returned at full size."""
    if scale >= 1:
        return lambda i: render(model, i)
    small = scaled_model(model, scale)
    return lambda i: render(model, i) if i in full_size else to_full_size(render(small, i), model.wh)


def fit_one(payload: dict) -> dict:
    """Runs in a Dask worker: fit, save checkpoint and renders, return table rows."""
    import torch

    from nerf.trainer import fit_window, validate

    wid, out_dir, data_root = payload["window_id"], Path(payload["out_dir"]), Path(payload["data_root"])
    frames = pd.DataFrame(payload["frames"])
    data = load_window(frames, data_root)
    key = str(wid)
    odometry = data.poses_c2w
    data.poses_c2w, depth_info = depth_initial_poses(payload["depth_poses"], data.depths, data.intrinsics, odometry)
    try:
        res = fit_window(data, payload["cfg"], device=payload["device"], render_val=not payload["panoptic"].enabled,
                         progress=lambda s, n, info: parallel.report(key, s, n, **info))
    except Exception as err:
        raise RuntimeError(f"window {wid}: {err}") from err
    wdir = out_dir / f"window_{wid:03d}"
    (wdir / "renders").mkdir(parents=True, exist_ok=True)
    state = res.model.state()
    pan = None
    pcfg = payload["panoptic"]
    if pcfg.enabled:
        from nerf.panoptic_fit import complete_instances, fit_panoptic, render_panoptic

        labels = load_labels(frames, pd.DataFrame(payload["detections"]) if payload["detections"] else None, data_root)
        try:
            pan = fit_panoptic(res.model, labels, data.is_train, data.depths, pcfg, seed=payload["cfg"].seed,
                               progress=lambda s, n, info: parallel.report(key, s, n, phase="panoptic", **info))
        except Exception as err:
            raise RuntimeError(f"window {wid} (panoptic phase): {err}") from err
        state["panoptic"] = pan.state()
        full = set(np.flatnonzero(frames[[c for c in ("is_center", "labelled") if c in frames]].any(axis=1)).tolist())
        validate(res, data, render_at(lambda m, i: render_panoptic(m, pan, i), res.model,
                                      payload.get("render_scale", 1.0), full))
        val = [int(i) for i in np.flatnonzero(~data.is_train)]
        complete_instances([res.renders[i] for i in val], data.intrinsics[val], res.poses_c2w[val], pan.cfg)
    torch.save(state, wdir / "checkpoint.pt")
    for i in np.flatnonzero(~data.is_train):
        out = res.renders[int(i)]
        fid = int(data.frame_ids[i])
        if pan is not None:
            write_png(wdir / "renders" / f"semantic_{fid:06d}.png", out["semantic"].astype(np.uint8))
            write_png(wdir / "renders" / f"instance_{fid:06d}.png", out["instance"].astype(np.uint16))
        rgb = (out["rgb"].clamp(0, 1).cpu().numpy() * 255).round().astype(np.uint8)
        depth_mm = np.clip(out["depth"].cpu().numpy() * 1000, 0, 65535).round().astype(np.uint16)
        write_png(wdir / "renders" / f"rgb_{fid:06d}.png", rgb)
        write_png(wdir / "renders" / f"depth_{fid:06d}.png", depth_mm)
    init = odometry
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
               "panoptic_steps": pan.steps if pan else 0, "panoptic_fit_s": pan.fit_s if pan else 0.0,
               "panoptic_params": pan.params if pan else 0,
               "panoptic_instances": bool(pan is not None and pan.cfg.instances), "n_slots": pan.n_slots if pan else 0,
               "id_window_width": pan.slot_window.width if pan and pan.slot_window else 0,
               **depth_info,
               "checkpoint": f"window_{wid:03d}/checkpoint.pt"}
    return {"poses": poses.to_dict("list"), "metrics": metrics}


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
    for wid in wids:
        w = windows[windows.window_id == wid].merge(frames, on="frame_id", how="left")
        if w["rgb_path"].isna().any():
            raise ValueError(f"window {wid}: frames {w.loc[w.rgb_path.isna(), 'frame_id'].tolist()} not in frames.parquet")
        w = initial_poses(w, int(wid), colmap, cfg.pose_source)
        payloads[str(wid)] = window_payload(int(wid), w, cfg, mcfg, ctx.device, out_dir, ctx.data_root,
                                            _window_detections(dets, w))
    n_workers = cfg.workers or parallel.default_workers(len(payloads))
    threads = cfg.threads_per_worker or max(1, (os.cpu_count() or 1) // n_workers)
    outcomes = parallel.map_tasks(fit_one, payloads, n_workers=n_workers, threads_per_worker=threads,
                                  scheduler=ctx.scheduler, show_progress=ctx.show_progress, desc="window")
    pose_tables, metric_rows = [], []
    for key in payloads:
        o = outcomes[key]
        wid = int(key)
        centre = int(windows.loc[windows.window_id == wid, "center_frame_id"].iloc[0])
        w = windows[windows.window_id == wid]
        base = {"window_id": wid, "center_frame_id": centre, "preset": mcfg.preset, "device": ctx.device,
                "n_train": int((w.split == "train").sum()), "n_val": int((w.split == "val").sum())}
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
                                "depth_pose_votes": 0, "depth_pose_note": ""})
            continue
        m = dict(o.result["metrics"])
        m["checkpoint_path"] = ctx.relpath("nerf", m.pop("checkpoint"))
        metric_rows.append({**base, **m})
        pose_tables.append(pd.DataFrame(o.result["poses"]))
    metrics = pd.DataFrame(metric_rows)
    poses = pd.concat(pose_tables, ignore_index=True) if pose_tables else None
    if poses is None:
        raise RuntimeError("nerf_fit: every window failed: " + "; ".join(metrics["error"]))
    ok = metrics[metrics.status == "ok"]
    ctx.summary.update(windows=len(metrics), failed=int((metrics.status != "ok").sum()),
                       mean_val_psnr=round(float(ok.val_psnr.mean()), 2), mean_fit_s=round(float(ok.fit_s.mean()), 1))
    return {"window_poses": poses, "window_metrics": metrics}
