"""Settings of the model library: the radiance field and its training (NerfConfig, with the presets L, S
and cpu), the panoptic phase (PanopticConfig), and the override layer a stage puts over a preset.

Lengths are metres unless a name says otherwise; positions inside the field are normalised (see
nerf/window.py `Scene`).
"""
from __future__ import annotations

import dataclasses
import typing
from dataclasses import dataclass, replace
from typing import Any, Literal

Preset = Literal["cpu", "S", "L"]
FieldKind = Literal["permuto", "mlp_pe"]
GridMode = Literal["delta", "shared", "independent"]


BASE_PIXELS = 320 * 180
"""Image size (pixels) the presets' ray budget is set for."""


@dataclass(frozen=True)
class NerfConfig:
    preset: Preset = "cpu"
    """model size preset: 'cpu' (sized for the default run on a 2-core machine), 'S' (9 levels, 2^15) or 'L'
    (21 levels, 2^18), the paper's two sizes for a GPU."""
    n_levels: int = 8
    """levels of the colour hash grid, from coarsest_res_m to finest_res_m (geometric). Range 1-32. More levels
    add detail scales at a proportional cost per sample."""
    n_features: int = 4
    """features per level of the colour grid (1-8). The field's feature width is n_levels x n_features."""
    log2_capacity: int = 19
    """log2 of the colour grid's hash table rows per level (range 10-24). The window's bounds reach the far
    plane, so the fine levels hold far more lattice vertices than the table has rows; raise it when fine
    texture blurs (hash collisions), lower it to save memory (table memory at most levels x 2^capacity x
    features x 4 bytes: a coarse level gets only the rows its vertices near the window's depth use,
    nerf.encoding.PermutoEncoding.size_levels)."""
    log2_capacity_delta: int = 12
    """log2 of the panoptic delta grid's table rows per level (range 8-24): the panoptic labels vary far more
    slowly than colour, so this grid can be much smaller."""
    finest_res_m: float = 0.003
    """finest lattice scale, metres (> 0, below coarsest_res_m). About the size of the smallest detail to
    resolve; finer than the pixel footprint at the working distance adds collisions, not detail."""
    coarsest_res_m: float = 0.5
    """coarsest lattice scale, metres: about the size of the largest structures of the scene."""
    hidden: int = 32
    """width of the hidden layers of the density and colour decoders (16-256). 32 on the CPU (the decoders are
    a third of a training step there); the GPU presets S and L keep 64. The panoptic heads: PanopticConfig.hidden."""
    field_kind: FieldKind = "permuto"
    """radiance field: 'permuto' (permutohedral hash grid + small decoders, nerf/fields/permuto.py) or
    'mlp_pe' (the Semantic-NeRF-like baseline: an MLP on a Fourier encoding, nerf/fields/mlp_pe.py)."""
    steps: int = 1200
    """optimisation steps of the colour phase (>= 1). Fit time grows linearly with it; the cpu preset is sized
    to fit a window in a few minutes on one core."""
    rays_per_step: int = 1024
    """rays per optimisation step for an image of up to BASE_PIXELS (320x180) pixels (>= 2: half carry the depth
    loss, half move the poses); larger images get more (rays_area_exponent, `rays_for`)."""
    rays_area_exponent: float = 0.25
    """>= 0: an image with more pixels than BASE_PIXELS trains on rays_per_step x (pixels / BASE_PIXELS) to this
    power rays per step (0.25: x1.41 at 640x360, x2 at 1280x720; 0 = rays_per_step at every size). A large
    image holds finer texture than the same rays see within the steps; the fit time grows about in proportion
    to the rays. Smaller images keep rays_per_step."""
    edge_ray_share: float = 0.25
    """share (0-1) of each step's rays drawn with probability proportional to the training image's colour
    gradient magnitude (the rest uniformly over the training pixels): most colour error sits on fine texture
    and occlusion edges. 0 = uniform rays."""
    lr_grid: float = 2e-2
    """Adam learning rate of the hash tables (normalised feature units; typical 5e-3 to 5e-2)."""
    lr_mlp: float = 1e-2
    """Adam learning rate of the decoders (typical 1e-3 to 2e-2)."""
    lr_decay: float = 0.1
    """the learning rates fall exponentially to this share (0-1] of their start value over the steps
    (1 = constant rate)."""
    lr_pose: float = 1e-4
    """Adam learning rate of the pose corrections (normalised scene units; rotation 6D entries). Raise it when
    the initial poses are far off, lower it when refined poses wander."""
    pose_warmup_steps: int = 200
    """steps (>= 0) before the poses start to move, so the geometry forms first."""
    pose_shift_penalty: float = 10.0
    """weight (>= 0, per m^2, 0 = none) of a penalty on how far the pose refinement moves the cameras, for a
    window whose parallax spread (nerf/window.py parallax_spread: the range of 1 / depth, 1/m) is 1/m; a
    window is fitted with pose_shift_penalty / spread^2 (per m^2, in window_metrics pose_shift_weight) times the
    mean over the refined frames of |translation correction|^2 (m^2), beside the colour MSE. Colour tells a
    sideways shift from a turn only by the parallax between near and far surfaces, so without the penalty
    positions wander along that ambiguity where the parallax is small (an office: spread 0.28/m, weight 124),
    while a near row (spread 1.5/m, weight 4) keeps what colour fixes. `pag bench pose_prior` measures it."""
    refine_poses: bool = True
    """optimise the training poses online from the colour loss (off = keep the initial poses)."""
    val_register_every: int = 100
    """register the validation poses to the frozen model every this many steps (>= 1)."""
    val_register_steps: int = 8
    """steps of each periodic validation-pose registration (the final one: val_register_final_steps)."""
    val_register_final_steps: int = 96
    """steps of the validation-pose registration after the last training step; the validation PSNR is
    measured at the poses it ends with, so too few steps report pose error as model error."""
    val_register_anneal: float = 0.1
    """the final registration's learning rate falls exponentially to this share (0-1] of its start over its
    steps: at a constant rate Adam leaves the poses jittering by about one step around their optimum."""
    val_register_edge_share: float = 0.5
    """share (0-1) of each registration step's rays drawn by the validation frames' colour gradient magnitude
    (like edge_ray_share): the pose gradient comes from image gradients, so rays on flat colour carry none."""
    depth_loss_weight: float = 0.02
    """weight (>= 0) of the depth L1 loss in metres, beside the colour MSE, on the half of the rays whose poses
    are detached (so depth never moves poses). 0 = colour only. Higher values sharpen geometry early but
    outweigh the colour loss once the model fits fine texture."""
    depth_edge_m: float = 0.05
    """pixels whose 3x3 neighbourhood in the sensor depth spans more than this (metres), or holds a pixel
    without depth, carry no depth loss (0 = every valid pixel): at a depth edge the pixel's colour mixes both
    surfaces and its expected depth lies between them. Raise it for noisy sensors on smooth scenes."""
    train_early_stop: float = 1e-3
    """training drops samples whose transmittance (from a density pass without gradients) is below this
    (0-1; 0 = keep all): samples hidden behind opaque surfaces cost a forward and a backward pass and teach
    nothing."""
    near_m: float = 0.15
    """near plane, metres (> 0): nothing closer to the camera is modelled."""
    far_m: float = 0.0
    """far plane, metres (> near_m; 0 = derived from each window's sensor depth: 1.1 x its 99th percentile,
    rounded up to 0.5 m, nerf/window.py depth_far_m). It sets the window's bounds and where rays stop, so it
    must cover everything visible (far row, back wall); set it only to force one value on every window."""
    cone_angle: float = 0.0129
    """radians (> 0): the marching step at depth t is cone_angle x t (cone marching; 0.0129 = 1.3 cm at 1 m,
    about three pixel footprints of a 320 px wide image across 69 degrees). It depends on the scene, not on the
    image size: a large image (1280x720) or a render at a working scale keeps the samples per ray, so a ray
    still reaches the far row within max_samples_per_ray. Smaller angles sample thin structures better at a
    proportional cost."""
    max_samples_per_ray: int = 96
    """cap on the samples per ray during training (>= 1)."""
    occupancy_res: int = 256
    """occupancy grid cells along the longest side of the window's bounds (16-1024). Finer cells leave fewer
    empty samples around surfaces; memory grows with its cube."""
    occupancy_dilate: int = 1
    """cells (>= 0) added around the depth-initialised occupancy, to cover pose and depth noise."""
    occupancy_every: int = 64
    """update the occupancy grid (EMA of density, pruning) every this many steps (>= 1)."""
    occupancy_threshold: float = 0.01
    """a cell stays occupied while its EMA opacity over one marching step exceeds this (0-1). Higher prunes
    more (faster, but may cut thin or faint surfaces)."""
    skip_empty: bool = True
    """sample only in occupied cells (off = every sample inside the window's bounds, for benchmarks)."""
    early_stop_transmittance: float = 1e-3
    """rendering stops a ray once its transmittance drops below this (0-1; 0 = march to the far plane)."""
    chunk_rays: int = 8192
    """rays per chunk when rendering images (>= 1): bounds the memory of a render, not its result."""
    seed: int = 0
    """random seed of the fit (initialisation and ray draws)."""

    def __post_init__(self) -> None:
        if not self.cone_angle > 0:
            raise ValueError(f"cone_angle must be > 0 (radians), got {self.cone_angle}")
        if not (self.far_m == 0 or self.far_m > self.near_m):
            raise ValueError(f"far_m must be 0 (derived from depth) or > near_m ({self.near_m}), got {self.far_m}")
        if not self.pose_shift_penalty >= 0:
            raise ValueError(f"pose_shift_penalty must be >= 0 (per m^2 at a parallax spread of 1/m; 0 = none), "
                             f"got {self.pose_shift_penalty}")
        if not self.rays_area_exponent >= 0:
            raise ValueError(f"rays_area_exponent must be >= 0, got {self.rays_area_exponent}")

    def rays_for(self, pixels: int) -> int:
        """Rays per step for images of `pixels` pixels (rays_per_step, grown by rays_area_exponent above
        BASE_PIXELS)."""
        if pixels <= BASE_PIXELS:
            return self.rays_per_step
        return int(round(self.rays_per_step * (pixels / BASE_PIXELS) ** self.rays_area_exponent))


PRESETS: dict[str, dict] = {
    "cpu": {},
    "S": dict(n_levels=9, n_features=2, log2_capacity=15, log2_capacity_delta=9, finest_res_m=0.003, steps=3000,
              rays_per_step=2048, hidden=64),
    "L": dict(n_levels=21, n_features=2, log2_capacity=18, log2_capacity_delta=18, finest_res_m=0.001, steps=6000,
              rays_per_step=4096, hidden=64),
}


def preset(name: str, **overrides) -> NerfConfig:
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; presets: {sorted(PRESETS)}")
    return replace(NerfConfig(preset=name, **PRESETS[name]), **overrides)  # type: ignore[arg-type]


@dataclass(frozen=True)
class PanopticConfig:
    enabled: bool = True
    """train the panoptic part and write semantic/instance renders (off = colour only)."""
    steps: int = 500
    """steps of the panoptic phase (after the colour phase; >= 0)."""
    frames_per_step: int = 4
    """training frames per step (>= 1; each frame's segments are assigned to slots on their own)."""
    rays_per_frame: int = 384
    """rays per frame and step (>= 1)."""
    hidden: int = 64
    """width of the semantic and instance heads' hidden layers (16-256): the instance head tells up to a hundred
    slots apart, and 32 wide its windows' ids were less consistent (docs/benchmarks.md)."""
    thing_ray_share: float = 0.5
    """share (0-1) of a frame's rays drawn from its thing (fruit) segments, so small fruits are not starved;
    importance weights keep the semantic loss unbiased."""
    grid_mode: GridMode = "delta"
    """panoptic features: 'delta' = a delta grid on top of the frozen colour grid (PAg-NeRF), 'shared' = the
    colour features themselves (panoptic losses then train them too; the only mode for a field without a hash
    grid), 'independent' = a full-size grid of its own."""
    n_slots: int = 0
    """instance slots including slot 0 = stuff (0 = automatic: 1 + 3 x the ID window width). Set it only to
    compare runs with a fixed head size; too few slots for the ID window is an error."""
    stuff_only_steps: int = 150
    """steps of the phase for a window without any thing detection in its training frames: only the
    semantic head is trained (no assignment, no instance head), and every rendered instance id is 0."""
    instances: bool = True
    """train and render instances (off = semantic only, the Semantic-NeRF-like baseline: every rendered
    instance id is 0, so all fruits of one class in a frame form one segment)."""
    id_window: bool = True
    """repeated-ID rejection: restrict each segment to the slot window at its position along the row."""
    id_window_margin: int = 4
    """slots (>= 0) added to the busiest training frame's segment count to give the ID window width. Raise it
    when the detector misses many fruits in the busiest frame."""
    position_prior: float = 0.05
    """with the ID window: weight (>= 0) of the slot preference from the segment's position along the row,
    which breaks the untrained head's ties alike in every frame (assignment costs lie in [-1, 0])."""
    memory_prior: float = 0.3
    """weight (>= 0) of the slot-memory term of the assignment cost (nerf/panoptic/assignment.py SlotMemory): a
    segment prefers the slot whose earlier segments lay at its 3D position and avoids slots of fruits
    elsewhere. 0 = off (plain assignment on the predicted probabilities)."""
    w_semantic: float = 1.0
    """weight (>= 0) of the confidence-weighted semantic cross entropy."""
    stuff_confidence: float = 0.5
    """confidence (0-1) of a stuff label (a pixel no detection covers) in the semantic loss; detections carry
    their score. Below 1 because a missing detection is weaker evidence than a detection: a detector misses a
    real fruit in many frames, while its false positives do not recur at one 3D place. 1 = trust stuff labels
    fully."""
    w_instance: float = 1.0
    """weight (>= 0) of the instance loss on thing rays (targets from the assignment)."""
    w_stuff: float = 1.0
    """weight (>= 0) of the loss pulling stuff rays to slot 0."""
    w_consistency: float = 0.1
    """weight (>= 0) of the segment-consistency loss (a weak pull of a segment's rays to one distribution)."""
    lr_grid: float = 1e-2
    """Adam learning rate of the panoptic grid (the colour grid gets a tenth of it in 'shared' mode)."""
    lr_mlp: float = 1e-2
    """Adam learning rate of the semantic and instance heads."""
    min_weight: float = 1e-2
    """samples with a smaller colour weight (0-1) skip the panoptic heads: they could move a ray's
    distribution by at most that weight. 0 = every sample (slower, same result within that weight)."""
    grow_threshold: float = 0.3
    """post-processing (hysteresis, 0-1): a pixel whose fruit probability exceeds this, though not the stuff
    classes', joins the fruit instance its most likely slot names when it touches that instance's sure
    pixels. Recovers the weakly labelled rims of fruits cut by the image border or half hidden, without
    creating new instances from weak evidence (1 = off)."""
    grow_depth_m: float = 0.02
    """post-processing: a pixel an instance grows into must have a rendered depth within this (metres, >= 0)
    of the instance's sure pixels' depth range, so a rim never spreads onto the leaf in front or the wall
    behind. About the fruit's depth extent seen from the camera."""
    min_segment_px: int = 12
    """post-processing: rendered instances smaller than this (pixels, after the 3x3 opening) are dropped.
    Scale it with the image area."""
    complete_3d: bool = True
    """post-processing over the window's rendered frames (nerf/panoptic/complete.py): each instance whose
    rendered pixels, un-projected with the rendered depth, fit a plausible sphere claims the stuff pixels of
    every frame whose 3D point lies inside that sphere. A fruit's side seen only where it enters or leaves
    the image is what the detector misses most; the fruit's 3D extent from the other frames says otherwise."""
    complete_margin_m: float = 0.005
    """a pixel lies inside a fruit's sphere when its 3D point is within the radius plus this (metres, >= 0;
    about the rendered depth error)."""
    complete_core: float = 0.7
    """3D completion by ray (0-1): a stuff pixel whose ray passes within this share of an instance's sphere
    radius of its centre, with a rendered depth not in front of where the ray enters that inner sphere (less
    complete_margin_m), also joins the instance: at a fruit's silhouette and along the image border the
    rendered depth blends into what lies behind, so the un-projected point misses the sphere though the ray
    crosses the fruit. Nothing in front of the fruit (a leaf) is taken. 0 = off; values near 1 take the
    background around the fruit."""
    complete_min_points: int = 100
    """an instance needs this many un-projected pixels (>= 4) over the window's frames for its sphere."""
    complete_max_radius_m: float = 0.06
    """largest plausible fruit radius for the sphere, metres (> 0; sweet pepper about 0.03-0.05 m). Too large
    lets a shallow cap's fit claim the leaves around a fruit; set it for the crop."""
    n_classes: int = 5
    """semantic classes (pipeline/classes.py)."""
    thing_classes: tuple[int, ...] = (2, 3, 4)
    """semantic classes that are things (have instances)."""

    def __post_init__(self) -> None:
        if not 0.0 <= self.stuff_confidence <= 1.0:
            raise ValueError(f"panoptic.stuff_confidence must lie in [0, 1], got {self.stuff_confidence}")
        if not 0.0 <= self.complete_core <= 1.0:
            raise ValueError(f"panoptic.complete_core must lie in [0, 1], got {self.complete_core}")
        if not 0.0 <= self.grow_threshold <= 1.0:
            raise ValueError(f"panoptic.grow_threshold must lie in [0, 1], got {self.grow_threshold}")
        if not self.grow_depth_m >= 0.0:
            raise ValueError(f"panoptic.grow_depth_m must be >= 0, got {self.grow_depth_m}")
        if not (self.complete_margin_m >= 0.0 and self.complete_max_radius_m > 0.0 and self.complete_min_points >= 4):
            raise ValueError("panoptic.complete_margin_m must be >= 0, complete_max_radius_m > 0 and "
                             f"complete_min_points >= 4; got {self.complete_margin_m}, {self.complete_max_radius_m}, "
                             f"{self.complete_min_points}")


def override_layer(cls: type, name: str, exclude: tuple[str, ...] = ()) -> type:
    """A frozen dataclass `name` with every field of the dataclass `cls` except `exclude`, each typed
    `T | None` with default None = "not set" (so every setting can be given and none has a sentinel). Its
    field docs are `cls`'s (`__docs_from__`). Apply it with `set_fields`."""
    hints = typing.get_type_hints(cls)
    fields = [(f.name, typing.Optional[hints[f.name]], dataclasses.field(default=None))
              for f in dataclasses.fields(cls) if f.name not in exclude]
    layer = dataclasses.make_dataclass(name, fields, frozen=True)
    layer.__module__ = cls.__module__
    layer.__doc__ = f"Overrides of {cls.__name__} settings: None = keep the value below this layer."
    layer.__docs_from__ = cls
    return layer


def set_fields(layer: Any) -> dict[str, Any]:
    """The fields of an override layer that are set (not None)."""
    return {f.name: getattr(layer, f.name) for f in dataclasses.fields(layer) if getattr(layer, f.name) is not None}


NerfOverrides = override_layer(NerfConfig, "NerfOverrides", exclude=("preset", "refine_poses", "seed"))
"""Overrides of a preset's model and training settings (`nerf_fit.model.<name>`); preset, refine_poses and
seed are set by the stage's own settings."""

REMOVED: dict[str, Any] = {"train_sampling": "occupancy", "surface_samples": None, "free_samples": None,
                           "truncate_at_depth": False, "opacity_loss_weight": 0.0, "depth_loss_fade": 0.0,
                           "max_step_m": 0.0, "stuff_border": 0.0, "slot_reach_m": 0.0, "region_reach_m": 0.0}
"""Settings a checkpoint may name that no longer exist, with the value that behaved as today (None = any:
it only acted together with another removed setting)."""


def config_from_state(cls: type, values: dict) -> Any:
    """`cls` (NerfConfig or PanopticConfig) from a checkpoint's settings, dropping removed settings that carry
    the value that behaved as today; a removed setting with another value is an error (the checkpoint was
    made by code that no longer exists)."""
    names = {f.name for f in dataclasses.fields(cls)}
    kept = {}
    for k, v in values.items():
        if k in names:
            kept[k] = tuple(v) if isinstance(v, list) else v
        elif k not in REMOVED:
            raise ValueError(f"checkpoint setting {k!r} is not a {cls.__name__} setting; settings: {sorted(names)}")
        elif REMOVED[k] is not None and v != REMOVED[k]:
            raise ValueError(f"checkpoint was made with {k}={v!r}, a setting that no longer exists (only "
                             f"{REMOVED[k]!r} is supported); refit the window")
    return cls(**kept)
