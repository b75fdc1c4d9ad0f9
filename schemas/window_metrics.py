"""window_metrics: per-window quality and cost of the NeRF fit."""
import pyarrow as pa

from schemas import col, table_schema

SCHEMA = table_schema(
    "window_metrics",
    "One row per window: the NeRF's validation quality, its cost, and where its checkpoint is.",
    col("window_id", pa.int32(), "window (windows.window_id)"),
    col("center_frame_id", pa.int32(), "labelled centre frame"),
    col("status", pa.string(), "'ok' or 'failed'"),
    col("error", pa.string(), "why the window failed ('' if ok), with the training step"),
    col("preset", pa.string(), "model preset (cpu, S, L)"),
    col("device", pa.string(), "torch device the window was fitted on"),
    col("threads", pa.int32(), "torch CPU threads the window's fit ended with (more than it started with where it "
        "took the cores of finished workers: nerf_fit.threads_per_worker = 0)"),
    col("n_train", pa.int32(), "training frames"),
    col("n_val", pa.int32(), "validation frames"),
    col("params", pa.int64(), "trainable parameters of the model (grids + decoders)"),
    col("steps", pa.int32(), "optimisation steps run"),
    col("fit_s", pa.float64(), "wall time of the fit", "s"),
    col("render_s_per_image", pa.float64(), "wall time to render one full validation image", "s"),
    col("samples_per_ray", pa.float64(), "mean samples evaluated per ray when rendering validation images", "samples"),
    col("val_psnr", pa.float64(), "mean PSNR over the validation frames (poses registered to the frozen model), each at "
        "the scale it was rendered at (nerf_fit.render_scale; the recorded image area-averaged to that size)", "dB"),
    col("train_psnr", pa.float64(), "mean PSNR over the training frames", "dB"),
    col("panoptic_steps", pa.int32(), "steps of the panoptic phase (0 = panoptic off)"),
    col("panoptic_fit_s", pa.float64(), "wall time of the panoptic phase (included in nothing else)", "s"),
    col("panoptic_params", pa.int64(), "trainable parameters of the panoptic part (delta grid + heads)"),
    col("panoptic_instances", pa.bool_(), "the instance part was trained (false: no thing detection in the "
        "window's training frames, so a short semantic-only phase ran and every instance id is 0)"),
    col("n_slots", pa.int32(), "instance slots of the window, slot 0 = stuff"),
    col("id_window_width", pa.int32(), "width of the repeated-ID rejection window in slots (0 = off)"),
    col("depth_poses", pa.string(), "how the initial poses were corrected with depth before the fit: 'icp' "
        "(trajectory shape from ICP), 'scale' (odometry scale only) or 'off' (nerf/depth_poses.py)"),
    col("odometry_scale", pa.float64(), "'scale' mode: stretch applied to the window's initial positions (1 = none); "
        "null otherwise", nullable=True),
    col("depth_pose_votes", pa.int32(), "'scale': frame pairs whose ICP voted; 'icp': consecutive-frame links taken "
        "from ICP"),
    col("depth_pose_note", pa.string(), "what was left to the odometry and why ('' if nothing)"),
    col("icp_max_depth_m", pa.float64(), "metres: depth limit of the ICP pose correction (nerf_fit.icp_max_depth_m, or "
        "derived from the window's depth); null with depth_poses 'off' or a failed window", nullable=True),
    col("far_m", pa.float64(), "metres: far plane of the window's field (nerf_fit.model.far_m, or derived from its "
        "depth); null for a failed window", nullable=True),
    col("pose_shift_weight", pa.float64(), "weight of the pose refinement's shift penalty: "
        "nerf_fit.model.pose_shift_penalty / the window's parallax spread^2 (nerf/trainer.py shift_weight; 0 with "
        "refinement off); null for a failed window", "1/m^2", nullable=True),
    col("peak_rss_mb", pa.float64(), "peak resident memory of the worker process over the window's fit, "
        "rendering and writing (the kernel's high-water mark; null where the system cannot reset it or the "
        "window failed)", "MiB", nullable=True),
    col("worker", pa.string(), "name of the dask worker that fitted the window ('' if it failed)"),
    col("checkpoint_path", pa.string(), "model checkpoint (torch.save), relative to data/; '' if failed"),
)
