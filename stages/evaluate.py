"""Score the windows' renders, the detector and the fused fruit map against ground truth (where it exists)."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

import schemas
from nerf.geometry import pose_matrix
from nerf.metrics import ate_rmse, rotation_error_deg
from pipeline.classes import THING_IDS, VOID
from pipeline.images import read_label
from pipeline.parallel import available_cores, in_order
from pipeline.stage import StageContext
from rowmap.renders import Renders
from rowmap.ground_truth import gt_poses_by_frame, match_fruits, to_ground_truth_frame  # noqa: F401 (also used by tests)
from rowmap.scoring import PanopticScore, image_pixels_for

INPUTS = ("raw", "frames", "windows", "window_poses", "window_metrics", "nerf", "renders", "gt_segments",
          "panoptic_frames", "panoptic", "fruits", "counts")
OUTPUTS = ("evaluation",)

POSE_COLS = ["tx", "ty", "tz"]
QUAT_COLS = ["qx", "qy", "qz", "qw"]
UNITS = {"psnr": "dB", "ate_odometry_m": "m", "ate_refined_m": "m", "rot_error_refined_deg": "deg",
         "rot_error_odometry_deg": "deg", "count_gt": "fruits", "count_pred": "fruits",
         "count_gt_near_row_all": "fruits", "fruits_matched": "fruits",
         "fruits_matched_unaligned": "fruits", "id_consistency_n_fruits": "fruits", "id_fail_unlabelled": "fruits",
         "id_fail_split": "fruits", "id_fail_shared": "fruits", "id_fail_one_frame": "fruits",
         "n_frames": "frames", "n_frames_detector": "frames"}


@dataclass(frozen=True)
class Config:
    match_max_distance_m: float = 0.05
    """metres, > 0. A predicted fruit matches a ground-truth fruit (Hungarian on centre distance, after moving
    the predicted centres into the ground-truth frame through the pose of a frame that saw them) only within
    this distance. About half a fruit diameter; larger values match neighbouring fruits."""
    min_frames_id: int = 3
    """frames, >= 1: fruits seen in at least this many frames are scored for ID consistency (and count as
    countable ground truth, count_gt)."""
    min_visible_px: int = 12
    """reference pixels (as in a 320x180 image: x16 at 1280x720), >= 1. ID consistency: a ground-truth fruit
    counts as visible in a frame where it covers at least this many; count_gt counts the fruits visible so in
    min_frames_id frames. Keep it at nerf_fit.panoptic.min_segment_px: the panoptic post-processing removes
    rendered segments below that size at the working scale (at most 320 px wide), so a fruit showing fewer
    cannot carry an id. In reference pixels the rule means the same share of the view at every image size."""

    def __post_init__(self) -> None:
        if not self.match_max_distance_m > 0:
            raise ValueError(f"evaluate.match_max_distance_m must be > 0, got {self.match_max_distance_m}")
        if self.min_frames_id < 1 or self.min_visible_px < 1:
            raise ValueError("evaluate.min_frames_id and evaluate.min_visible_px must be >= 1")


def void_far(sem: np.ndarray, inst: np.ndarray, far_ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Ground truth with the fruits the depth filter dropped (the far row) set to void: nobody is asked to
    segment them, and a prediction lying on them is neither right nor wrong."""
    if len(far_ids) == 0:
        return sem, inst
    far = np.isin(inst, far_ids) & np.isin(sem, THING_IDS)
    return np.where(far, VOID, sem), np.where(far, 0, inst)


class GroundTruth:
    """Per-frame ground-truth panoptic images (far-row fruits voided) and the near-row fruit ids."""

    def __init__(self, frames: pd.DataFrame, gt_segments: pd.DataFrame, data_root: Path):
        self.frames = frames
        self.root = data_root
        seg = gt_segments
        self.far = {int(f): g.instance_id.to_numpy() for f, g in seg[~seg.kept.astype(bool)].groupby("frame_id")}
        self.near = {int(f): g.instance_id.to_numpy() for f, g in seg[seg.kept.astype(bool)].groupby("frame_id")}

    def has(self, fid: int) -> bool:
        fr = self.frames.loc[fid]
        return isinstance(fr.gt_semantic_path, str) and isinstance(fr.gt_instance_path, str)

    def load(self, fid: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        fr = self.frames.loc[fid]
        sem = read_label(self.root / fr.gt_semantic_path, f"ground-truth semantic of frame {fid}")
        inst = read_label(self.root / fr.gt_instance_path, f"ground-truth instance of frame {fid}")
        sem, inst = void_far(sem, inst, self.far.get(fid, np.array([], int)))
        return sem, inst, self.near.get(fid, np.array([], int))


def load_pred(sem_path: Path, inst_path: Path, shape: tuple[int, int], what: str):
    sem = read_label(sem_path, f"{what} semantic")
    inst = read_label(inst_path, f"{what} instance")
    if sem.shape != shape or inst.shape != shape:
        raise ValueError(f"{what}: {sem_path} {sem.shape} / {inst_path} {inst.shape} differ from the ground "
                         f"truth's {shape}")
    return sem, inst


def window_scores(inputs: dict, gt: GroundTruth, gt_poses: pd.DataFrame | None, cfg: Config,
                  ctx: StageContext) -> list[tuple[str, str, float]]:
    frames, windows = gt.frames, inputs["windows"]
    poses, metrics = inputs["window_poses"], inputs["window_metrics"]
    renders = Renders(inputs["renders"], ctx.data_root)
    rows = []
    for m in ctx.progress(metrics.itertuples(index=False), "windows", total=len(metrics)):
        wid = int(m.window_id)
        scope = f"window_{wid:03d}"
        if m.status != "ok":
            ctx.count("windows_failed_not_scored")
            continue
        out: dict[str, float] = {"psnr": float(m.val_psnr)}
        nerf, det = PanopticScore(cfg.min_visible_px), PanopticScore(cfg.min_visible_px)

        def score(fid: int) -> tuple[PanopticScore | None, PanopticScore | None]:
            """Frame fid's (render score, detector score), None where there is nothing to score; on a worker
            thread."""
            g_sem, g_inst, near = gt.load(fid)
            by_nerf = by_det = None
            if renders.has(wid, fid, "semantic", "instance"):
                sp, ip = (gt.root / renders.relpath(wid, fid, k) for k in ("semantic", "instance"))
                by_nerf = nerf.image(*load_pred(sp, ip, g_sem.shape, f"window {wid} render of frame {fid}"),
                                     g_sem, g_inst, near)
            fr = frames.loc[fid]
            if isinstance(fr.det_semantic_path, str) and isinstance(fr.det_instance_path, str):
                by_det = det.image(*load_pred(gt.root / fr.det_semantic_path, gt.root / fr.det_instance_path,
                                              g_sem.shape, f"detector output of frame {fid}"), g_sem, g_inst, near)
            return by_nerf, by_det

        val = windows[(windows.window_id == wid) & (windows.split == "val")].frame_id.astype(int)
        for by_nerf, by_det in in_order(score, [f for f in val if gt.has(f)], available_cores()):
            for total, one in ((nerf, by_nerf), (det, by_det)):
                if one is not None:
                    total.add(one)
        if nerf.n == 0 and len(val):
            ctx.count("windows_without_panoptic_scores")
        out.update(nerf.metrics(cfg.min_frames_id))
        out.update(det.metrics(cfg.min_frames_id, "_detector"))
        out.update(n_frames=float(nerf.n), n_frames_detector=float(det.n))
        if gt_poses is not None:
            wp = poses[poses.window_id == wid].merge(gt_poses, on="frame_id", suffixes=("", "_gt"))
            wp = wp.merge(frames[["frame_id", *POSE_COLS, *QUAT_COLS]].reset_index(drop=True), on="frame_id",
                          suffixes=("", "_odo"))
            if len(wp):
                g = wp[[f"{c}_gt" for c in POSE_COLS]].to_numpy()
                out["ate_refined_m"] = ate_rmse(wp[POSE_COLS].to_numpy(), g)
                out["ate_odometry_m"] = ate_rmse(wp[[f"{c}_odo" for c in POSE_COLS]].to_numpy(), g)
                # with a scale in the alignment too: the trajectory's shape, whatever its length
                out["ate_refined_sim3_m"] = ate_rmse(wp[POSE_COLS].to_numpy(), g, "sim3")
                out["ate_odometry_sim3_m"] = ate_rmse(wp[[f"{c}_odo" for c in POSE_COLS]].to_numpy(), g, "sim3")
                if set(f"{c}_gt" for c in QUAT_COLS) <= set(wp.columns):
                    rot = lambda sfx: pose_matrix(wp[[f"{c}{sfx}" for c in POSE_COLS + QUAT_COLS]].to_numpy())[:, :3, :3]  # noqa: E731
                    out["rot_error_refined_deg"] = rotation_error_deg(rot(""), rot("_gt"))
                    out["rot_error_odometry_deg"] = rotation_error_deg(rot("_odo"), rot("_gt"))
        rows += [(scope, k, v) for k, v in out.items()]
    return rows


def countable_fruits(gt_segments: pd.DataFrame, near_ids: set[int], image_pixels: int, cfg: Config) -> list[int]:
    """Ground-truth near-row fruits the recording shows well enough to count: at least cfg.min_visible_px
    reference pixels (kept by the depth filter; images of `image_pixels` pixels) in at least
    cfg.min_frames_id frames of the row, the population the ID consistency is scored on. A fruit glimpsed in
    one or two frames at the start or end of the recording is left out (count_gt_near_row_all and
    count_error_rel_all include it)."""
    seg = gt_segments[gt_segments.kept.astype(bool) &
                      (gt_segments.area_px >= image_pixels_for(cfg.min_visible_px, image_pixels))]
    frames = seg.groupby("instance_id").frame_id.nunique()
    return sorted(int(i) for i, n in frames.items() if n >= cfg.min_frames_id and int(i) in near_ids)


def row_scores(inputs: dict, gt: GroundTruth, gt_fruits: pd.DataFrame | None, gt_poses: pd.DataFrame | None,
               cfg: Config, ctx: StageContext) -> list[tuple[str, str, float]]:
    pf: pd.DataFrame = inputs["panoptic_frames"]
    out: dict[str, float] = {}
    fused = PanopticScore(cfg.min_visible_px)

    def score(r) -> PanopticScore:
        """The fused frame r's score (on a worker thread)."""
        g_sem, g_inst, near = gt.load(int(r.frame_id))
        return fused.image(*load_pred(gt.root / r.semantic_path, gt.root / r.instance_path, g_sem.shape,
                                      f"fused frame {r.frame_id}"), g_sem, g_inst, near)

    scored = [r for r in pf.itertuples(index=False) if gt.has(int(r.frame_id))]
    for one in ctx.progress(in_order(score, scored, available_cores()), "fused frames", total=len(scored)):
        fused.add(one)
    out.update(fused.metrics(cfg.min_frames_id))
    if gt_fruits is not None:
        fruits = inputs["fruits"]
        pred = fruits[fruits.counted.astype(bool)]
        near_ids = set(gt_fruits.loc[gt_fruits.near_row.astype(bool), "fruit_id"].astype(int))
        image_px = int(gt.frames.width.max()) * int(gt.frames.height.max())
        seen = countable_fruits(inputs["gt_segments"], near_ids, image_px, cfg)
        g = gt_fruits.set_index("fruit_id").loc[seen]
        n_gt, n_pred, n_all = len(g), int(inputs["counts"]["count"].sum()), len(near_ids)
        out.update(count_gt=float(n_gt), count_pred=float(n_pred),
                   count_error_rel=(n_pred - n_gt) / n_gt if n_gt else float("nan"),
                   count_gt_near_row_all=float(n_all),
                   count_error_rel_all=(n_pred - n_all) / n_all if n_all else float("nan"))
        gxyz = g[["x_m", "y_m", "z_m"]].to_numpy(np.float64)
        raw = pred[["x_m", "y_m", "z_m"]].to_numpy(np.float64)
        aligned = to_ground_truth_frame(pred, gt.frames, gt_poses, pf)
        raw_matches = match_fruits(raw, gxyz, cfg.match_max_distance_m)
        out["fruits_matched_unaligned"] = float(len(raw_matches))
        matches = match_fruits(aligned, gxyz, cfg.match_max_distance_m)
        out.update(fruits_matched=float(len(matches)),
                   fruit_recall=len(matches) / n_gt if n_gt else float("nan"),
                   fruit_precision=len(matches) / len(pred) if len(pred) else float("nan"))
        if matches:
            pi, gi, dist = (np.array(v) for v in zip(*matches))
            gd = g.diameter_m.to_numpy()[gi]
            out["centre_error_mean_m"] = float(dist.mean())
            for col, name in (("diameter_m", "diameter"), ("diameter_spheroid_m", "diameter_spheroid"),
                              ("diameter_sphere_m", "diameter_sphere"), ("diameter_pca_m", "diameter_pca")):
                err = pred[col].to_numpy(np.float64)[pi] - gd
                err = err[np.isfinite(err)]
                if len(err):
                    out[f"{name}_mae_m"] = float(np.abs(err).mean())
                    out[f"{name}_bias_m"] = float(err.mean())
                    if name == "diameter":
                        out["diameter_median_abs_err_m"] = float(np.median(np.abs(err)))
            # other definitions of the truth, where the ground truth carries them (synthetic rows: the widest
            # caliper reading and the pepper's shape parameter)
            for ref in ("diameter_max_m", "diameter_nominal_m"):
                if ref in g.columns:
                    err = pred["diameter_m"].to_numpy(np.float64)[pi] - g[ref].to_numpy(np.float64)[gi]
                    err = err[np.isfinite(err)]
                    if len(err):
                        name = ref.removesuffix("_m")
                        out[f"diameter_vs_{name}_median_abs_err_m"] = float(np.median(np.abs(err)))
                        out[f"diameter_vs_{name}_bias_m"] = float(err.mean())
            out["class_accuracy"] = float(np.mean(pred.class_id.to_numpy()[pi] == g.class_id.to_numpy()[gi]))
    return [("row", k, v) for k, v in out.items()]


def unit(metric: str) -> str:
    if metric in UNITS:
        return UNITS[metric]
    if metric.endswith("_m"):
        return "m"
    return "fraction" if metric.split("_")[0] in {"pq", "sq", "rq", "miou", "id", "fruit", "class", "count"} else ""


def run(inputs: dict, cfg: Config, ctx: StageContext) -> dict[str, pd.DataFrame]:
    gt_dir = Path(inputs["raw"]) / "gt"
    frames = inputs["frames"].set_index("frame_id", drop=False)
    gt_poses = pd.read_parquet(gt_dir / "poses.parquet") if (gt_dir / "poses.parquet").is_file() else None
    gt_fruits = pd.read_parquet(gt_dir / "fruits.parquet") if (gt_dir / "fruits.parquet").is_file() else None
    for name, t, need in (("poses", gt_poses, {"stamp_ns", *POSE_COLS}),
                          ("fruits", gt_fruits, {"fruit_id", "class_id", "x_m", "y_m", "z_m", "diameter_m", "near_row"})):
        if t is not None and not need <= set(t.columns):
            raise ValueError(f"evaluate: {gt_dir / (name + '.parquet')} lacks columns {sorted(need - set(t.columns))}; "
                             f"columns: {list(t.columns)} (data/README.md, 'Ground truth: gt/')")
    if gt_poses is not None:
        gt_poses = gt_poses_by_frame(gt_poses, frames)
        missing = len(frames) - len(gt_poses)
        if missing:
            ctx.count("frames_without_gt_pose", missing)
            ctx.note(f"{missing} of {len(frames)} frames have no pose in {gt_dir / 'poses.parquet'} within half a frame "
                     f"period of their stamp; pose errors are scored on the others")
    has_panoptic_gt = frames.gt_semantic_path.notna().any()
    if gt_poses is None and gt_fruits is None and not has_panoptic_gt:
        ctx.note(f"no ground truth ({gt_dir} absent and no labelled frames): nothing to evaluate, table empty")
        return {"evaluation": schemas.empty("evaluation")}
    gt = GroundTruth(frames, inputs["gt_segments"], ctx.data_root)
    rows = window_scores(inputs, gt, gt_poses, cfg, ctx)
    per_window = pd.DataFrame(rows, columns=["scope", "metric", "value"])
    means = per_window.groupby("metric", sort=False).value.mean()
    rows += [("windows_mean", k, float(v)) for k, v in means.items()]
    rows += row_scores(inputs, gt, gt_fruits, gt_poses, cfg, ctx)
    out = pd.DataFrame(rows, columns=["scope", "metric", "value"])
    out["value"] = out["value"].astype(np.float64)
    out["unit"] = [unit(m) for m in out.metric]
    row = out[out.scope == "row"].set_index("metric").value
    for k in ("count_gt", "count_pred", "id_consistency", "diameter_mae_m"):
        if k in row:
            ctx.summary[f"row_{k}"] = round(float(row[k]), 4)
    for k in ("pq", "miou", "pq_detector", "psnr"):
        if k in means:
            ctx.summary[f"mean_{k}"] = round(float(means[k]), 4)
    return {"evaluation": out}
