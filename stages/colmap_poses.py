"""Optional: COLMAP poses of each window's frames, mapped into the odometry frame by a similarity transform."""
from __future__ import annotations

import os
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from nerf.geometry import align_similarity, apply_similarity, pose_matrix, pose_txyzq, rotation_angle_deg
from pipeline.stage import StageContext
from schemas import empty

INPUTS = ("frames", "windows", "images")
OUTPUTS = ("colmap_poses",)
POSE_COLS = ["tx", "ty", "tz", "qx", "qy", "qz", "qw"]


@dataclass(frozen=True)
class Config:
    enabled: bool = False
    """run COLMAP (off: `pag all` leaves the stage out; run alone it writes an empty table). Turn it on to
    start nerf_fit from COLMAP poses (nerf_fit.pose_source=colmap) or to compare them with the odometry."""
    min_registered: int = 3
    """frames, >= 2, COLMAP must register in a window (and keep after the residual checks) before its poses are
    used; else the window keeps odometry. Raise it to trust only well-registered windows."""
    overlap: int = 10
    """frames, >= 1: sequential matching pairs each frame with this many following frames. Raise it when
    consecutive frames overlap little (fast motion), at a matching cost growing linearly with it."""
    max_features: int = 8192
    """features, >= 1: SIFT features extracted per image at most. Lower it on large images to save time."""
    sift_peak_threshold: float = 0.004
    """> 0: SIFT detection threshold. Lower finds more (weaker) features; COLMAP's default 0.0067 finds too few
    on small, low-contrast images of foliage."""
    min_inliers: int = 30
    """matches, >= 1: verified matches needed for the initial image pair and for registering a further
    image. Lower it for small images (fewer features), raise it when frames are registered wrongly."""
    min_tri_angle_deg: float = 4.0
    """degrees, > 0: triangulation angle the initial pair needs. COLMAP's 16 deg is more than a short window
    along a row offers; raise it with wide-baseline windows."""
    orientation_weight: float = 1.0
    """>= 0: weight of the camera orientations against the centres in the alignment to odometry
    (nerf.geometry.align_similarity; 0 = plain Umeyama on the centres, whose rotation about a straight
    trajectory is undetermined). Keep it > 0 for straight tracks along a row."""
    max_residual_m: float = 0.05
    """metres, > 0. A registered frame whose aligned position is farther than this from its odometry position
    falls back to odometry and takes no part in the alignment (pairs of frames are tried as hypotheses, see
    robust_similarity). About the odometry's drift over a window; lower it to reject more registrations."""
    max_rot_residual_deg: float = 5.0
    """degrees, > 0: likewise for the angle between a frame's aligned and its odometry orientation (a short,
    narrow-baseline reconstruction can be consistently tilted). About the odometry's orientation error over a
    window."""
    threads: int = 1
    """COLMAP threads, >= 0 (0 = all cores). With one thread the poses are repeatable; with several, COLMAP's
    mapper can register a different set of frames from run to run, fewer on a loaded machine. The stage's
    time is small beside nerf_fit's."""
    seed: int = 0
    """COLMAP's random seed (RANSAC and the mapper); change it to check how much the poses depend on it."""

    def __post_init__(self) -> None:
        if self.min_registered < 2:
            raise ValueError(f"colmap_poses.min_registered must be >= 2, got {self.min_registered}")
        for name in ("overlap", "max_features", "min_inliers"):
            if getattr(self, name) < 1:
                raise ValueError(f"colmap_poses.{name} must be >= 1, got {getattr(self, name)}")
        for name in ("sift_peak_threshold", "min_tri_angle_deg", "max_residual_m", "max_rot_residual_deg"):
            if not getattr(self, name) > 0:
                raise ValueError(f"colmap_poses.{name} must be > 0, got {getattr(self, name)}")
        if self.orientation_weight < 0 or self.threads < 0:
            raise ValueError("colmap_poses.orientation_weight and colmap_poses.threads must be >= 0")


# -- COLMAP ---------------------------------------------------------------------------------------
def _pycolmap():
    try:
        import pycolmap
    except ImportError as err:  # the dependency is declared; this is for broken installs
        raise RuntimeError(f"colmap_poses.enabled=true needs pycolmap, which cannot be imported ({err}); "
                           "reinstall it with `.venv/bin/pip install pycolmap`") from err
    return pycolmap


def reconstruct(image_paths: dict[int, Path], k: tuple[float, float, float, float], cfg: Config,
                workdir: Path) -> dict[int, np.ndarray]:
    """COLMAP on one window: frame id -> image file, PINHOLE intrinsics (fx, fy, cx, cy) in pixels ->
    frame id -> camera-to-world [4, 4] in the reconstruction's own frame and units, for the frames of the
    largest model (empty if COLMAP finds none)."""
    pycolmap = _pycolmap()
    img_dir = workdir / "images"
    img_dir.mkdir(parents=True)
    names = {}
    for fid, path in sorted(image_paths.items()):
        name = f"{fid:06d}{path.suffix}"  # zero-padded: sequential matching follows the name order
        try:
            os.symlink(path.resolve(), img_dir / name)
        except OSError:
            shutil.copyfile(path, img_dir / name)
        names[name] = fid
    db = workdir / "database.db"
    threads = cfg.threads or -1
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "PINHOLE"
    reader.camera_params = ",".join(f"{v:.10g}" for v in k)
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = threads
    extraction.sift.max_num_features = cfg.max_features
    extraction.sift.peak_threshold = cfg.sift_peak_threshold
    pycolmap.extract_features(db, img_dir, image_names=sorted(names), camera_mode=pycolmap.CameraMode.SINGLE,
                              reader_options=reader, extraction_options=extraction)
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = threads
    pairing = pycolmap.SequentialPairingOptions()
    pairing.overlap = cfg.overlap
    verify = pycolmap.TwoViewGeometryOptions()
    verify.ransac.random_seed = cfg.seed
    pycolmap.match_sequential(db, matching_options=matching, pairing_options=pairing, verification_options=verify)
    opts = pycolmap.IncrementalPipelineOptions()
    opts.num_threads = threads
    opts.random_seed = cfg.seed
    opts.min_model_size = cfg.min_registered
    opts.min_num_matches = min(15, cfg.min_inliers)
    # the intrinsics are known: keep the PINHOLE camera fixed
    opts.ba_refine_focal_length = False
    opts.ba_refine_principal_point = False
    opts.ba_refine_extra_params = False
    opts.mapper.abs_pose_refine_focal_length = False
    opts.mapper.abs_pose_refine_extra_params = False
    opts.mapper.init_min_tri_angle = cfg.min_tri_angle_deg
    opts.mapper.init_min_num_inliers = cfg.min_inliers
    opts.mapper.abs_pose_min_num_inliers = min(cfg.min_inliers, opts.mapper.abs_pose_min_num_inliers)
    models = pycolmap.incremental_mapping(db, img_dir, workdir / "sparse", options=opts)
    if not models:
        return {}
    rec = max(models.values(), key=lambda m: m.num_reg_images())
    out = {}
    for im in rec.images.values():
        if not im.has_pose:
            continue
        cfw = im.cam_from_world() if callable(im.cam_from_world) else im.cam_from_world
        w2c = np.eye(4)
        w2c[:3, :] = np.asarray(cfw.matrix(), np.float64)
        out[names[im.name]] = np.linalg.inv(w2c)
    return out


class _Quiet:
    """Keeps COLMAP's INFO log off the terminal while the stage runs (restored afterwards)."""

    def __enter__(self):
        self.log = getattr(_pycolmap(), "logging", None)
        self.level = getattr(self.log, "minloglevel", None)
        if self.level is not None:
            self.log.minloglevel = 2
        return self

    def __exit__(self, *exc):
        if self.level is not None:
            self.log.minloglevel = self.level


# -- one window -----------------------------------------------------------------------------------
MAX_HYPOTHESES = 2000
"""pairs of frames tried as alignment hypotheses per window (all pairs up to 63 registered frames)."""


def _fit(col: np.ndarray, odo: np.ndarray, sel: np.ndarray, cfg: Config):
    """Similarity fitted on the frames `sel` -> (s, aligned poses [M, 4, 4], position residuals [M] m,
    orientation residuals [M] deg, inliers [M] bool)."""
    s, r, t = align_similarity(col[sel, :3, 3], odo[sel, :3, 3], col[sel, :3, :3], odo[sel, :3, :3],
                               orientation_weight=cfg.orientation_weight)
    aligned = apply_similarity(s, r, t, col)
    res_t = np.linalg.norm(aligned[:, :3, 3] - odo[:, :3, 3], axis=1)
    res_r = rotation_angle_deg(aligned[:, :3, :3], odo[:, :3, :3])
    return s, aligned, res_t, res_r, (res_t <= cfg.max_residual_m) & (res_r <= cfg.max_rot_residual_deg)


def robust_similarity(col: np.ndarray, odo: np.ndarray, cfg: Config):
    """Outlier-robust alignment of COLMAP poses col [M, 4, 4] to odometry poses odo [M, 4, 4]: every pair
    of frames (two centres and their orientations fix a similarity) is a hypothesis, the one with the most
    inliers (smaller RMS residual on ties) wins and is refitted on its inliers until they stop changing.
    A plain least-squares fit is not enough: one misregistered frame a few decimetres off can shrink the
    scale of a short window until every residual looks small. Returns `_fit`'s tuple, or None."""
    m = len(col)
    pairs = [(i, j) for i in range(m) for j in range(i + 1, m)]
    if len(pairs) > MAX_HYPOTHESES:
        pick = np.random.default_rng(cfg.seed).choice(len(pairs), MAX_HYPOTHESES, replace=False)
        pairs = [pairs[k] for k in np.sort(pick)]
    best, best_key = None, None
    for i, j in pairs:
        sel = np.zeros(m, bool)
        sel[[i, j]] = True
        try:
            fit = _fit(col, odo, sel, cfg)
        except ValueError:  # coincident centres: no scale from this pair
            continue
        key = (int(fit[4].sum()), -float(np.sqrt(np.mean(fit[2][fit[4]] ** 2))) if fit[4].any() else -np.inf)
        if best_key is None or key > best_key:
            best, best_key = fit, key
    for _ in range(5):
        if best is None or best[4].sum() < 2:
            return None
        try:
            fit = _fit(col, odo, best[4], cfg)
        except ValueError:
            return best
        done = (fit[4] == best[4]).all()
        if fit[4].sum() < best[4].sum():
            return best
        best = fit
        if done:
            break
    return best


def align_window(wid: int, frame_ids: np.ndarray, odo_c2w: np.ndarray, colmap_c2w: dict[int, np.ndarray],
                 cfg: Config) -> tuple[pd.DataFrame, dict[str, int]]:
    """Rows of the colmap_poses table for one window and its counts. Odometry poses [N, 4, 4] of
    `frame_ids`; COLMAP poses by frame id (any subset). Registered frames whose position or orientation
    residual after the robust alignment exceeds cfg.max_residual_m / max_rot_residual_deg fall back to
    odometry; windows with fewer than cfg.min_registered frames left keep their odometry poses."""
    n = len(frame_ids)
    pose = odo_c2w.copy()
    source = np.array(["odometry"] * n, dtype=object)
    res_t = np.full(n, np.nan)
    res_r = np.full(n, np.nan)
    rmse, scale = np.nan, np.nan
    have = np.array([int(f) in colmap_c2w for f in frame_ids])
    counts = {"frames": n, "frames_not_registered": int((~have).sum()), "frames_rejected_residual": 0,
              "windows_without_colmap": 0}
    use = np.zeros(n, bool)
    idx = np.flatnonzero(have)
    fit = None
    if len(idx) >= cfg.min_registered:
        fit = robust_similarity(np.stack([colmap_c2w[int(f)] for f in frame_ids[idx]]), odo_c2w[idx], cfg)
    if fit is not None and fit[4].sum() >= cfg.min_registered:
        scale, aligned, res_t[idx], res_r[idx], inl = fit
        use[idx[inl]] = True
        pose[use] = aligned[inl]
        source[use] = "colmap"
        rmse = float(np.sqrt(np.mean(res_t[use] ** 2)))
        counts["frames_rejected_residual"] = int((~inl).sum())
    else:
        counts["windows_without_colmap"] = 1
    q = pose_txyzq(pose)
    df = pd.DataFrame({"window_id": np.full(n, wid, np.int32), "frame_id": frame_ids.astype(np.int32),
                       "registered": use, "source": source.astype(str),
                       **{c: q[:, j] for j, c in enumerate(POSE_COLS)},
                       "residual_m": res_t, "rot_residual_deg": res_r,
                       "window_rmse_m": np.full(n, rmse), "scale": np.full(n, scale)})
    return df, counts


def window_colmap(wid: int, w: pd.DataFrame, cfg: Config, data_root: Path, work_dir: Path
                  ) -> tuple[pd.DataFrame, dict[str, int]]:
    """COLMAP poses of one window's frames (`w`: windows rows merged with frames, sorted by frame), aligned to
    the odometry: the window's colmap_poses rows and counts (as align_window), plus registered_by_colmap."""
    if w["rgb_path"].isna().any():
        raise ValueError(f"colmap_poses: window {wid}: frames {w.loc[w.rgb_path.isna(), 'frame_id'].tolist()} "
                         f"are not in frames.parquet")
    k = w[["fx", "fy", "cx", "cy"]].drop_duplicates()
    if len(k) != 1:
        raise ValueError(f"colmap_poses: window {wid} mixes {len(k)} different intrinsics "
                         f"{k.to_dict('records')}; one fixed PINHOLE camera per window is expected")
    paths = {int(f): data_root / p for f, p in zip(w["frame_id"], w["rgb_path"])}
    missing = [f"{f}: {p}" for f, p in paths.items() if not p.is_file()]
    if missing:
        raise FileNotFoundError(f"colmap_poses: window {wid}: colour images missing: {missing[:5]}"
                                f"{' ...' if len(missing) > 5 else ''}; rerun `pag ingest`")
    with _Quiet():
        col = reconstruct(paths, tuple(float(v) for v in k.iloc[0]), cfg, work_dir)
    odo = pose_matrix(w[POSE_COLS].to_numpy(np.float64))
    df, counts = align_window(wid, w["frame_id"].to_numpy(), odo, col, cfg)
    return df, {**counts, "registered_by_colmap": len(col)}


def run(inputs: dict, cfg: Config, ctx: StageContext) -> dict[str, pd.DataFrame]:
    if not cfg.enabled:
        ctx.note("disabled (colmap_poses.enabled=false): empty table written; nerf_fit starts from odometry")
        ctx.summary.update(windows=0, frames=0)
        return {"colmap_poses": empty("colmap_poses")}
    frames: pd.DataFrame = inputs["frames"]
    windows: pd.DataFrame = inputs["windows"]
    if windows.empty:
        raise ValueError("colmap_poses: the windows table is empty; nothing to reconstruct")
    tables, totals = [], {}
    with tempfile.TemporaryDirectory(prefix="pag_colmap_") as tmp:
        wids = sorted(int(w) for w in windows["window_id"].unique())
        for wid in ctx.progress(wids, "window", total=len(wids)):
            w = windows[windows.window_id == wid].merge(frames, on="frame_id", how="left").sort_values("frame_id")
            df, counts = window_colmap(wid, w, cfg, ctx.data_root, Path(tmp) / f"window_{wid:03d}")
            tables.append(df)
            for key, v in counts.items():
                totals[key] = totals.get(key, 0) + v
            if counts["windows_without_colmap"]:
                ctx.note(f"window {wid}: COLMAP registered {counts['registered_by_colmap']} of {len(w)} frames, fewer "
                         f"than min_registered={cfg.min_registered} of them fit the odometry; the window keeps its "
                         f"odometry poses")
    out = pd.concat(tables, ignore_index=True)
    n_col = int(out["registered"].sum())
    ctx.summary.update(windows=len(tables), frames=len(out), frames_colmap=n_col,
                       frames_odometry_fallback=len(out) - n_col, **{k: v for k, v in totals.items() if k not in ("frames", "registered_by_colmap")},
                       median_window_rmse_m=round(float(np.nanmedian(out.drop_duplicates("window_id")["window_rmse_m"])), 4)
                       if out["window_rmse_m"].notna().any() else None)
    if n_col < len(out):
        ctx.note(f"{len(out) - n_col} of {len(out)} (window, frame) poses fall back to odometry "
                 f"({totals['frames_not_registered']} not registered by COLMAP, "
                 f"{totals['frames_rejected_residual']} with an alignment residual > {cfg.max_residual_m} m or "
                 f"{cfg.max_rot_residual_deg} deg, {totals['windows_without_colmap']} window(s) without a usable model)")
    return {"colmap_poses": out}
