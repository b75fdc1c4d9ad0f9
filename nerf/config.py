"""Model and training settings, with the presets L, S and cpu."""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Literal

Preset = Literal["cpu", "S", "L"]


@dataclass(frozen=True)
class NerfConfig:
    preset: Preset = "cpu"
    """model size preset: cpu (default run on 2 cores), S (9 levels, 2^15) or L (21 levels, 2^18)."""
    n_levels: int = 8
    """levels of the colour grid."""
    n_features: int = 4
    """features per level."""
    log2_capacity: int = 19
    """log2 of the colour grid's hash table size per level. The window's bounds reach the back wall 3.5 m away,
    so the fine levels hold far more lattice vertices than a small table has rows and the hash collisions cost
    more than anything else: default row, window 1, 10 levels of 2 features, edge_ray_share 0.25, one core per
    fit side by side: 2^16 -> val 25.9 dB (fit 106 s), 2^18 -> 26.2 (115 s), 2^19 -> 26.9 (130 s), 2^20 -> 26.8
    (151 s). At 2^19 (finest 3 mm): 2 features x 10 levels 26.9 dB (130 s), 4 x 10 27.4 (168 s), 4 x 8 27.4
    (161 s; windows 0 / 2: 26.6 / 26.9 dB, 143 / 151 s), 4 x 6 27.0 (137 s), 8 x 5 26.8 (159 s); 4 x 8 at 2^18
    27.1 (146 s). The cpu preset is 4 x 8 at 2^19 (16.8 M table parameters, 67 MB)."""
    log2_capacity_delta: int = 12
    """log2 of the panoptic delta grid's table size per level."""
    finest_res_m: float = 0.003
    """finest lattice scale, metres (window 1 at 2^19, 10 x 2: 4 mm -> 26.86 dB, 3 mm -> 26.94)."""
    coarsest_res_m: float = 0.5
    """coarsest lattice scale, metres."""
    hidden: int = 64
    """width of the decoders' hidden layers."""
    field_kind: Literal["permuto", "mlp_pe"] = "permuto"
    """radiance field: 'permuto' (hash grid + small decoders, ours) or 'mlp_pe' (the Semantic-NeRF-like
    baseline: an MLP on a Fourier encoding of position and direction, nerf/baselines.py)."""
    steps: int = 1200
    """optimisation steps (the cpu preset is sized for under 3 minutes per window with 2 workers on 2 cores, with
    a margin: the same fit runs up to a quarter slower in the pipeline than alone in a process). Default row,
    window 1, the cpu preset, depth_loss_weight 0.02, side by side: 1200 steps -> val 27.9 dB in 129 s, 1300 ->
    28.0 dB in 141 s (in one pipeline run of the harder variant 1300 steps took 180 s on window 1: over the
    budget's margin). With depth_loss_weight 0.1: 1300 steps -> 27.1 dB in 138 s, 1500 -> 27.4 dB in 161 s. Older
    model (10 x 2, 2^16): 600 -> 1500 steps 21.4 -> 24.1 dB, 1500 -> 1900 24.3 -> 24.2."""
    rays_per_step: int = 1024
    """rays per step."""
    edge_ray_share: float = 0.25
    """share of each step's rays drawn with probability proportional to the training image's colour gradient
    magnitude (the rest uniformly over the training pixels): most of the colour error sits on fine texture and
    occlusion edges. Default row (10 levels x 2 features, 2^16), val PSNR of windows 0 / 1 / 2: 0 -> 24.8 / 25.3
    / 25.1 dB, 0.25 -> 25.1 / 25.9 / 25.2; window 1 with 0.5: 25.7."""
    lr_grid: float = 2e-2
    """Adam learning rate of the hash tables (default row, window 1, cpu preset: 0.01 -> val 27.0 dB, 0.02 ->
    27.1, 0.04 -> 27.0)."""
    lr_mlp: float = 1e-2
    """Adam learning rate of the decoders (window 1: 0.005 -> 26.9 dB, 0.01 -> 27.1, 0.02 -> 27.0)."""
    lr_decay: float = 0.1
    """the learning rates fall exponentially to this share of their start value over the steps (default row,
    window 1, edge_ray_share 0.25: 0.01 -> val 25.2 dB, 0.03 -> 25.4, 0.1 -> 25.9)."""
    lr_pose: float = 1e-4
    """Adam learning rate of the pose corrections (normalised scene units; rotation 6D entries)."""
    pose_warmup_steps: int = 200
    """steps before the poses start to move (let the geometry form first)."""
    refine_poses: bool = True
    """optimise the train poses online from the colour loss."""
    val_register_every: int = 100
    """register the validation poses to the frozen model every this many steps."""
    val_register_steps: int = 8
    """steps of each periodic validation-pose registration (the final one: val_register_final_steps)."""
    val_register_final_steps: int = 96
    """steps of the validation-pose registration after the last training step (the validation PSNR is measured
    at the poses it ends with)."""
    val_register_anneal: float = 0.1
    """the final registration's learning rate falls exponentially to this share of its start over its steps.
    At a constant rate Adam leaves the poses jittering by about one step around their optimum (a tenth of a
    pixel of rotation matters on fine texture). Measured on one frozen model per window (default row, windows
    2 / 0, the periodic registrations uniform, then each final registration from the same poses), val PSNR:
    no final registration 27.59 / 27.36 dB; 48 steps as before (constant rate, uniform rays) 27.25 / 27.29;
    48 annealed to 0.1 28.30 / 28.12; 48 with half the rays on edges 27.92 / 27.68; both 28.42 / 28.26; both
    with 96 steps 28.52 / 28.33 (3 s more); with 2048 rays 28.59 / 28.38 (8 s more again)."""
    val_register_edge_share: float = 0.5
    """share of each registration step's rays drawn by the validation frames' colour gradient magnitude (like
    edge_ray_share): the pose gradient comes from image gradients, so uniform rays on flat colour carry none."""
    depth_loss_weight: float = 0.02
    """weight of the depth loss (only on rays whose poses are detached, so it never moves poses). An L1 in metres
    beside a colour MSE: at 0.1 it outweighed the colour loss once the model could fit fine texture. Default row,
    window 1, the cpu preset at 1300 steps, one core per fit side by side (rendered depth against the sensor's on
    the validation pixels nearer than 1.5 m): 0.1 -> val 27.1 dB, depth error median 2.9 mm (p90 49 mm); 0.05 ->
    27.5 dB; 0.03 -> 27.5 dB; 0.02 -> 28.0 dB, 4.2 mm (p90 78 mm); 0.01 -> 28.0 dB, 5.0 mm (p90 84 mm). Whole rows,
    0.1 -> 0.02 (1300 steps): default row mean val PSNR 26.5 -> 27.7 dB, PQ 0.908 -> 0.921, fruit diameter median
    error 3.4 -> 3.6 mm (MAE 6.4 -> 4.4 mm), ID consistency 1.0 -> 0.96 (two fruits at the recording's ends);
    harder variant 26.6 -> 27.6 dB, PQ 0.905 -> 0.919, row ID consistency 0.81 -> 0.89, count 35 -> 37 of 38."""
    depth_edge_m: float = 0.05
    """pixels whose 3x3 neighbourhood in the sensor depth spans more than this (metres), or holds a pixel
    without depth, get no depth loss (0 = every valid pixel): at a depth edge the pixel's colour mixes both
    surfaces, which the field can only render by a soft edge whose expected depth lies between them. Default
    row, window 1, 1900 steps, constant weight 0.1: off -> val 24.2 dB, rendered depth median error 10.8 mm;
    0.05 -> 25.0 / 24.4 dB (seeds 0 / 1), 6.7 / 7.3 mm; 0.02 -> 23.9 dB, 6.3 mm."""
    depth_loss_fade: float = 0.0
    """share of the steps over which the depth loss weight falls linearly to 0 (0 = constant weight):
    depth shapes the geometry early, colour alone refines it and the poses later. Default row, window 1
    (6 val frames, occupancy_res 256, 1900 steps, one seed, depth_edge_m off): constant 0.1 -> val PSNR
    24.2 dB, rendered depth median error 11 mm (vs sensor, < 1.5 m); constant 0.03 -> 25.1 dB, 13 mm; fade
    0.4 -> 25.8 dB, 19 mm (with depth_edge_m 0.05: 25.6 dB, 14 mm). A whole row with fade 0.4 gave mean val
    PSNR 25.7 dB but a fruit diameter median error of 6.5 mm (3.8 mm without): kept off, the fruit map
    measures fruits from the rendered depth. A Huber (smooth L1) depth loss did not help PSNR either."""
    opacity_loss_weight: float = 0.0
    """weight of the opacity loss: 1 - opacity reached by the sensor depth (plus a margin), on the rays with
    valid depth whose poses are detached; makes surfaces opaque so nothing behind them shows in renders
    (0.1 measured -0.5 dB on the default row with truncation off: kept off)."""
    train_early_stop: float = 1e-3
    """training drops samples whose transmittance (from a density pass without gradients) is below this
    (0 = keep all): the samples hidden behind opaque surfaces cost a forward and a backward pass and teach nothing
    (default row: 60 -> 48 training samples per ray, same PSNR)."""
    truncate_at_depth: bool = False
    """training rays stop a margin past the sensor depth (off = march to the far plane like rendering). On:
    whatever lies behind a not yet opaque surface is never trained but renders show it; measured on the default
    row (600 steps) val PSNR 17.4 dB (training frames rendered: 17.4, training batches 22.5) against 21.4 off."""
    near_m: float = 0.15
    """near plane."""
    far_m: float = 3.5
    """far plane (covers the far row and the back wall)."""
    step_scale: float = 3.0
    """marching step = step_scale * pixel footprint at the sample's depth (cone marching)."""
    train_sampling: Literal["depth", "occupancy"] = "occupancy"
    """training samples: 'depth' = a band around the sensor depth plus free-space samples in front
    (RGB-D rays), 'occupancy' = cone marching through the occupancy grid like rendering. 'depth' measured
    poorly on the default row (12 samples per ray, 4096 rays: val 14.8 dB; the occupied cells in front of
    the band stay untrained and renders see them)."""
    surface_samples: int = 8
    """samples in the band around the sensor depth (train_sampling = depth)."""
    free_samples: int = 4
    """samples in the free space in front of the sensor depth (train_sampling = depth)."""
    max_step_m: float = 0.0
    """cap on the marching step (0 = none): keeps distant surfaces (far row, wall) from being undersampled."""
    max_samples_per_ray: int = 96
    """cap on samples per ray during training."""
    occupancy_res: int = 256
    """occupancy grid cells along the longest side of the window's bounds. Finer cells leave fewer empty samples
    around surfaces: default row, window 1, 1500 steps: 128 -> 55.7 training samples per ray, fit 234 s, val
    24.6 dB; 256 -> 31.3, 136 s, 24.3 dB (measured side by side, one core each); 192 (1900 steps) -> 43.5."""
    occupancy_dilate: int = 1
    """cells added around the depth-initialised occupancy (covers pose and depth noise)."""
    occupancy_every: int = 64
    """update the occupancy grid (EMA of density, pruning) every this many steps."""
    occupancy_threshold: float = 0.01
    """a cell stays occupied while its EMA opacity over one marching step exceeds this."""
    skip_empty: bool = True
    """sample only in occupied cells (off = every sample inside the window's bounds, for benchmarks)."""
    early_stop_transmittance: float = 1e-3
    """rendering stops a ray once its transmittance drops below this (0 = never: march to the far plane)."""
    chunk_rays: int = 8192
    """rays per chunk when rendering images."""
    seed: int = 0
    """random seed of the fit."""


PRESETS: dict[str, dict] = {
    "cpu": {},
    "S": dict(n_levels=9, n_features=2, log2_capacity=15, log2_capacity_delta=9, finest_res_m=0.003, steps=3000,
              rays_per_step=2048),
    "L": dict(n_levels=21, n_features=2, log2_capacity=18, log2_capacity_delta=18, finest_res_m=0.001, steps=6000,
              rays_per_step=4096),
}


def preset(name: str, **overrides) -> NerfConfig:
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; presets: {sorted(PRESETS)}")
    return replace(NerfConfig(preset=name, **PRESETS[name]), **overrides)  # type: ignore[arg-type]
