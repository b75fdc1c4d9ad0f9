"""The panoptic phase of a window's fit, and panoptic rendering.

After the colour phase (trainer.fit_window) the radiance field, the occupancy grid and the poses are
frozen; this phase trains only the panoptic part (nerf/panoptic.py: delta grid + semantic and instance
heads) from the detector's per-frame segments of the training frames:

    L = w_sem * L_sem + w_inst * L_inst + w_stuff * L_stuff + w_cons * L_cons      (nerf/panoptic_losses.py)

Each step takes a few training frames and rays in each (half of them on thing segments, so small
fruits are not starved), renders them with the frozen colour field (no gradient: the colour weights
are detached anyway, so panoptic losses can move neither density nor poses), integrates the
semantic and instance probabilities, assigns each frame's thing segments to instance slots with
linear_sum_assignment (nerf/assignment.py) and takes a step on the losses. With repeated-ID
rejection on, a segment may only take the slots of the sliding window at its 3D position along the
trajectory (its rays un-projected with the rendered depth); the slot memory adds a cost that draws a
segment to the slot whose earlier segments lay where it lies (nerf/assignment.SlotMemory). Stuff labels
weigh `stuff_confidence` in the semantic loss (a missed detection is weak evidence of no fruit).

Samples whose colour weight is below `min_weight` do not reach the panoptic heads (they could move a
ray's distribution by at most that weight); this is what makes the phase cheap.
"""
from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from typing import Literal

import numpy as np
import torch
from scipy import ndimage
from torch import Tensor

from nerf.assignment import SlotMemory, SlotWindow, along_track, assign, position_preference, segment_costs, segment_geometry
from nerf.field import param_count
from nerf.panoptic import PanopticField, integrate_probs
from nerf.panoptic_losses import consistency_loss, instance_loss, semantic_loss
from nerf.surfaces import fit_sphere, plausible_fit, principal_extents, robust_centre, unproject
from nerf.render import Rounds, composite_weights, pixel_rays

VOID = 255


@dataclass(frozen=True)
class PanopticConfig:
    enabled: bool = True
    """train the panoptic part and write semantic/instance renders (off = colour only)."""
    steps: int = 500
    """steps of the panoptic phase (after the colour phase)."""
    frames_per_step: int = 4
    """training frames per step (each frame's segments are assigned to slots on their own)."""
    rays_per_frame: int = 384
    """rays per frame and step."""
    thing_ray_share: float = 0.5
    """share of a frame's rays drawn from its thing (fruit) segments."""
    grid_mode: Literal["delta", "shared", "independent"] = "delta"
    """panoptic features: delta grid on top of the frozen colour grid (PAg-NeRF), the colour grid itself
    ('shared', panoptic losses then train it too), or an independent full-size grid."""
    n_slots: int = 0
    """instance slots including slot 0 = stuff (0 = automatic: 1 + 3 x the ID window width)."""
    stuff_only_steps: int = 150
    """steps of the phase for a window without any thing detection in its training frames: only the
    semantic head is trained (no assignment, no instance head), and every rendered instance id is 0."""
    instances: bool = True
    """train and render instances (off = semantic only, the Semantic-NeRF-like baseline: every rendered
    instance id is 0, so all fruits of one class in a frame form one segment)."""
    id_window: bool = True
    """repeated-ID rejection: restrict each segment to the slot window at its position along the row."""
    id_window_margin: int = 4
    """slots added to the busiest training frame's segment count to give the ID window width."""
    position_prior: float = 0.05
    """with the ID window: weight of the slot preference from the segment's position along the row, which
    breaks the untrained head's ties alike in every frame (costs lie in [-1, 0])."""
    memory_prior: float = 0.3
    """weight of the slot-memory term of the assignment cost (nerf/assignment.SlotMemory): a segment prefers
    the slot whose earlier segments lay at its 3D position (the same fruit seen from another frame) and
    avoids slots of fruits elsewhere. 0 = off (plain assignment on the predicted probabilities)."""
    w_semantic: float = 1.0
    """weight of the confidence-weighted semantic cross entropy."""
    stuff_confidence: float = 0.5
    """confidence of a stuff label (a pixel no detection covers) in the semantic loss; detections carry their
    score. Below 1 because the absence of a detection is weaker evidence than a detection: a detector misses
    a real fruit in many frames (partly hidden or cut by the image border), while its false positives do not
    recur at one 3D place, so the multi-view vote still rejects them. 1 = trust stuff labels fully."""
    stuff_border: float = 0.0
    """stuff labels within this share of the image's shorter side from the image border are void: a fruit cut
    by the border is what a detector misses most, and the side of a fruit that faces the direction of travel
    is seen only near the border, so those labels would teach that side to be stuff (0 = trust them). Measured
    on the default row, window 1: 0.05 raised ID consistency 0.86 -> 0.93 but lowered PQ 0.907 -> 0.835 (the
    unlabelled border strips of the window's first and last frames render wrong classes): off by default."""
    w_instance: float = 1.0
    """weight of the instance loss on thing rays (targets from the assignment)."""
    w_stuff: float = 1.0
    """weight of the loss pulling stuff rays to slot 0."""
    w_consistency: float = 0.1
    """weight of the segment-consistency loss."""
    lr_grid: float = 1e-2
    """Adam learning rate of the panoptic grid."""
    lr_mlp: float = 1e-2
    """Adam learning rate of the semantic and instance heads."""
    min_weight: float = 1e-2
    """samples with a smaller colour weight skip the panoptic heads."""
    grow_threshold: float = 0.3
    """post-processing (hysteresis): a pixel whose fruit probability exceeds this, though not the stuff
    classes', joins the fruit instance its most likely slot names when it touches that instance's sure
    pixels. Recovers the weakly labelled rims of fruits cut by the image border or half hidden, without
    creating new instances from weak evidence (1 = off)."""
    grow_depth_m: float = 0.02
    """post-processing: a pixel an instance grows into must have a rendered depth within this of the
    instance's sure pixels' depth range, so a rim never spreads onto the leaf in front or the wall behind."""
    min_segment_px: int = 12
    """post-processing: rendered instances smaller than this (after the 3x3 opening) are dropped."""
    complete_3d: bool = True
    """post-processing over the window's rendered frames (complete_instances): each instance whose rendered
    pixels, un-projected with the rendered depth, fit a plausible sphere claims the stuff pixels of every
    frame whose 3D point lies inside that sphere. A fruit's side seen only where it enters or leaves the
    image is what the detector misses most, so the 2D head calls it plant; the fruit's 3D extent from the
    other frames says otherwise."""
    complete_margin_m: float = 0.005
    """a pixel lies inside a fruit's sphere when its 3D point is within the radius plus this (rendered depth
    error)."""
    complete_core: float = 0.7
    """3D completion by ray: a stuff pixel whose ray passes within this share of an instance's sphere radius
    of its centre, with a rendered depth not in front of where the ray enters that inner sphere (less
    complete_margin_m), also joins the instance: at a fruit's silhouette and along the image border the
    rendered depth blends into what lies behind, so the un-projected point misses the sphere though the ray
    crosses the fruit. Nothing in front of the fruit (a leaf) is taken. 0 = off. Default row, saved renders
    of the three windows: 0.7 -> PQ -0.2 / -0.1 / +0.05 points, ID consistency of window 2 0.93 -> 1.0 (a
    fruit's one-pixel strip at the border); 0.85 -> PQ -0.7 to -1.4 points; 1.0 -> -4.5 to -6.5."""
    complete_min_points: int = 100
    """an instance needs this many un-projected pixels over the window's frames for its sphere."""
    complete_max_radius_m: float = 0.06
    """largest plausible fruit radius for the sphere (sweet pepper: about 0.03-0.05 m). Default row: 0.08 let a
    cap's sphere fit of 7 cm claim the leaves around a 4 cm fruit (window 1 PQ 0.899 -> 0.863)."""
    region_reach_m: float = 0.0
    """rendering (0 = off, the default): when one slot paints several regions of a frame, a region lying
    farther than this from the slot's largest region there (3D centres, rendered depth) takes the slot,
    among those whose largest region in the frame lies within this distance of it, that the head gives the
    most probability over it (kept when there is none). Meant for a fruit entering a window's last frames
    that is painted partly with the slot of a fruit 44 cm away beside its own (harder variant). Measured
    with 0.12 on the default row: window 0 ID consistency 1.0 -> 0.94, row 1.0 -> 0.96, count 25 -> 26,
    PQ 0.901 -> 0.900: off."""
    slot_reach_m: float = 0.0
    """rendering (0 = off, the default): a rendered instance region (one slot's connected pixels in a frame)
    whose 3D centre lies farther than this from where the slot's training segments placed it (the slot
    memory's running centre) takes the slot, among those placed within this distance of it, that the head
    gives the most probability over the region (kept when there is none). Meant for a fruit entering a
    window's last frames that the head paints with the slot of a fruit 40 cm away (harder variant). Measured
    with 0.12 on the default row: ID consistency unchanged (1.0), PQ 0.899 -> 0.893 and count 25 -> 27
    vs 25: the running centre of a slot that training gave to two places (a fruit and a detector false
    positive) lies at neither, and regions moved onto it became a second fruit in the fusion."""
    n_classes: int = 5
    """semantic classes (pipeline/classes.py)."""
    thing_classes: tuple[int, ...] = (2, 3, 4)
    """semantic classes that are things (have instances)."""

    def __post_init__(self) -> None:
        if not 0.0 <= self.stuff_confidence <= 1.0:
            raise ValueError(f"panoptic.stuff_confidence must lie in [0, 1], got {self.stuff_confidence}")
        if not 0.0 <= self.complete_core <= 1.0:
            raise ValueError(f"panoptic.complete_core must lie in [0, 1], got {self.complete_core}")
        if not 0.0 <= self.stuff_border < 0.5:
            raise ValueError(f"panoptic.stuff_border must lie in [0, 0.5), got {self.stuff_border}")
        if not 0.0 <= self.grow_threshold <= 1.0:
            raise ValueError(f"panoptic.grow_threshold must lie in [0, 1], got {self.grow_threshold}")
        if not self.grow_depth_m >= 0.0:
            raise ValueError(f"panoptic.grow_depth_m must be >= 0, got {self.grow_depth_m}")
        if not (self.complete_margin_m >= 0.0 and self.complete_max_radius_m > 0.0 and self.complete_min_points >= 4):
            raise ValueError("panoptic.complete_margin_m must be >= 0, complete_max_radius_m > 0 and "
                             f"complete_min_points >= 4; got {self.complete_margin_m}, {self.complete_max_radius_m}, "
                             f"{self.complete_min_points}")


@dataclass
class WindowLabels:
    """The detector's per-frame panoptic input of a window, aligned with WindowData's frames."""

    semantic: np.ndarray
    """[N, H, W] uint8 class id, 255 = void (no detection, or a segment the depth filter dropped)."""
    instance: np.ndarray
    """[N, H, W] int32 per-frame segment id (0 = stuff / none); ids mean nothing across frames."""
    confidence: np.ndarray
    """[N, H, W] float32 detector confidence of the pixel's segment (1 for stuff, 0 for void)."""

    def __post_init__(self) -> None:
        if not (self.semantic.shape == self.instance.shape == self.confidence.shape):
            raise ValueError(f"WindowLabels shapes differ: semantic {self.semantic.shape}, instance "
                             f"{self.instance.shape}, confidence {self.confidence.shape}")
        self.confidence = np.nan_to_num(self.confidence.astype(np.float32), nan=0.0, posinf=1.0, neginf=0.0).clip(0, 1)

    def take(self, idx: np.ndarray) -> "WindowLabels":
        """The labels of the frames `idx` only, in that order."""
        return WindowLabels(self.semantic[idx], self.instance[idx], self.confidence[idx])


@dataclass
class PanopticResult:
    field: PanopticField
    cfg: PanopticConfig
    slot_window: SlotWindow | None
    n_slots: int
    steps: int
    fit_s: float
    params: int
    history: list[dict] = field(default_factory=list)
    assignments: int = 0
    """segment-to-slot assignments made."""
    overflow_segments: int = 0
    """segments that found no free slot in their frame (more segments than slots)."""
    instances_skipped: bool = False
    """the window's training frames had no thing detection: a semantic-only phase of cfg.stuff_only_steps ran."""
    frames_without_things: int = 0
    """frame draws whose assignment was skipped because the frame has no thing segment."""
    frames_assigned: int = 0
    """frame draws whose thing segments were assigned to slots."""
    assign_s: float = 0.0
    """wall time of the assignments (costs, ID window, slot memory, linear_sum_assignment)."""
    slot_centres: np.ndarray | None = None
    """[n_slots, 3] world position of each slot's fruit from the assignments (the slot memory); NaN for a
    slot no segment took (and for slot 0)."""

    def state(self) -> dict:
        return {"cfg": asdict(self.cfg), "field": self.field.state_dict(), "n_slots": self.n_slots,
                "slot_window": asdict(self.slot_window) if self.slot_window else None,
                "slot_centres": None if self.slot_centres is None else self.slot_centres.tolist()}


def panoptic_field(model, cfg: PanopticConfig, n_slots: int) -> PanopticField:
    """The panoptic part sized after the colour grid of `model` (trainer.NerfModel)."""
    mc = model.cfg
    if hasattr(model.field, "panoptic_field"):  # a field without a hash grid builds its own heads (nerf/baselines.py)
        return model.field.panoptic_field(cfg, n_slots, mc.hidden)
    enc = model.field.grid
    cap = mc.log2_capacity_delta if cfg.grid_mode == "delta" else mc.log2_capacity
    return PanopticField(mc.n_levels, mc.n_features, cap, float(enc.scales[0]), float(enc.scales[-1]), cfg.n_classes,
                         n_slots, mode=cfg.grid_mode, hidden=mc.hidden, seed=mc.seed + 1)


@dataclass
class KeptSamples:
    """Samples of a ray batch that carry colour weight, with what the panoptic heads need."""

    x: Tensor        # [S, 3] normalised positions
    g: Tensor        # [S, L*F] colour-grid features (detached unless the grid is shared)
    w: Tensor        # [S] colour weights (detached)
    ray_index: Tensor
    n_rays: int
    rgb: Tensor      # [R, 3]
    depth: Tensor    # [R] z-depth, metres (expected termination depth / opacity)
    opacity: Tensor  # [R]
    n_evaluated: int


def weighted_samples(model, o: Tensor, d: Tensor, min_weight: float, round_samples: int = 32,
                     keep_grad_features: bool = False) -> KeptSamples:
    """March rays through the frozen colour model in rounds with early termination (as rendering does)
    and keep the samples with weight >= min_weight."""
    n = o.shape[0]
    dev = o.device
    cfg = model.cfg
    edges = model.edges(dev)
    occ = model.occupied_fn()
    eps = cfg.early_stop_transmittance
    rgb = torch.zeros(n, 3, device=dev)
    depth = torch.zeros(n, device=dev)
    trans = torch.ones(n, device=dev)
    active = torch.arange(n, device=dev)
    xs, gs, ws, rs = [], [], [], []
    n_eval = 0
    with torch.no_grad():
        rounds = Rounds(o, d, edges, occ)
    r = 0
    while active.numel():
        with torch.no_grad():
            s = rounds.take(active, r * round_samples, round_samples)
        if len(s) == 0:
            break
        with torch.set_grad_enabled(keep_grad_features):
            sigma, col, x, g = model.shade(o[active], d[active], s)
        with torch.no_grad():
            w, left = composite_weights(sigma.detach(), s.delta, s.ray_index, s.n_rays)
            w = w * trans[active][s.ray_index]
            ray = active[s.ray_index]
            rgb.index_add_(0, ray, w[:, None] * col.detach())
            depth.index_add_(0, ray, w * s.t_mid)
            keep = w >= min_weight
            had = torch.bincount(s.ray_index, minlength=s.n_rays) >= round_samples
            trans[active] = trans[active] * left
        xs.append(model.scene.normalise(x.detach()[keep]))
        gs.append(g[keep] if keep_grad_features else g.detach()[keep])
        ws.append(w[keep])
        rs.append(ray[keep])
        n_eval += len(s)
        active = active[had & (trans[active] > eps)]
        r += 1
    opacity = 1 - trans
    width = model.field.feature_dim
    cat = lambda parts, shape: torch.cat(parts) if parts else torch.zeros(shape, device=dev)  # noqa: E731
    ray_index = cat(rs, (0,)).long()
    order = torch.argsort(ray_index, stable=True)
    return KeptSamples(cat(xs, (0, 3))[order], cat(gs, (0, width))[order], cat(ws, (0,))[order], ray_index[order], n,
                       rgb, depth / opacity.clamp_min(1e-6), opacity, n_eval)


def ray_probs(pfield: PanopticField, ks: KeptSamples) -> tuple[Tensor, Tensor]:
    """Per-ray semantic [R, D] and instance [R, N] distributions (rows sum to 1)."""
    if len(ks.w) == 0:
        d, n = pfield.semantic[-1].out_features, pfield.instance[-1].out_features
        return torch.full((ks.n_rays, d), 1.0 / d), torch.full((ks.n_rays, n), 1.0 / n)
    sem_logits, inst_logits = pfield(ks.x, ks.g)
    return (integrate_probs(sem_logits, ks.w, ks.ray_index, ks.n_rays),
            integrate_probs(inst_logits, ks.w, ks.ray_index, ks.n_rays))


def slot_window_for(labels: WindowLabels, is_train: np.ndarray, depths: np.ndarray, k: np.ndarray,
                    cfg: PanopticConfig) -> tuple[SlotWindow, int]:
    """ID window width from the busiest training frame (+ margin), frustum length = the image's
    horizontal footprint at the median depth of the detected things; slots = 1 + 3 x width unless set."""
    things = np.isin(labels.semantic, cfg.thing_classes)
    busiest = 1
    for i in np.flatnonzero(is_train):
        ids = np.unique(labels.instance[i][things[i]])
        busiest = max(busiest, int((ids > 0).sum()))
    d = depths[things & (depths > 0)]
    if d.size == 0:
        d = depths[depths > 0]
    z = float(np.median(d)) if d.size else 1.0
    w_px = 2 * float(np.median(k[:, 2]))
    frustum_m = max(w_px / float(np.median(k[:, 0])) * z, 1e-3)
    width = busiest + cfg.id_window_margin
    n_slots = cfg.n_slots or 1 + 3 * width
    if n_slots - 1 < 2 * width:
        raise ValueError(f"panoptic.n_slots = {n_slots} is too few for the ID window: the busiest training frame "
                         f"has {busiest} thing segments, so the window is {width} slots wide and needs at least "
                         f"{2 * width + 1} slots; raise panoptic.n_slots or set it to 0 (automatic)")
    return SlotWindow.for_scene(busiest, frustum_m, n_slots, margin=cfg.id_window_margin), n_slots


def _draw_pixels(sem: np.ndarray, things: np.ndarray, n: int, share: float,
                 rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Flat pixel indices of one frame, `share` of them on thing pixels and the rest over the labelled
    (non-void) pixels, with each draw's importance weight p/q (p = uniform over labelled pixels, q = the
    mixture actually sampled; scaled to a maximum of 1), so that the semantic loss sees the classes in
    their true proportions."""
    thing_px = np.flatnonzero(things)
    labelled_px = np.flatnonzero(sem != VOID)
    pool = labelled_px if labelled_px.size else np.arange(sem.size)
    n_thing = int(round(n * share)) if thing_px.size else 0
    s = n_thing / n
    picks = [thing_px[rng.integers(0, thing_px.size, n_thing)]] if n_thing else []
    picks.append(pool[rng.integers(0, pool.size, n - n_thing)])
    px = np.concatenate(picks)
    on_thing = things.ravel()[px]
    q = (1 - s) / pool.size + np.where(on_thing, s / max(thing_px.size, 1), 0.0)
    w = (1.0 / pool.size) / q
    return px, w / w.max()  # <= 1: the semantic loss takes weights in [0, 1]


def fit_panoptic(model, labels: WindowLabels, is_train: np.ndarray, depths: np.ndarray, cfg: PanopticConfig,
                 progress: Callable[[int, int, dict], None] | None = None, seed: int = 0) -> PanopticResult:
    """Train the panoptic part of a fitted window (model = trainer.NerfModel with its final poses)."""
    t0 = time.perf_counter()
    dev = model.poses_c2w.device
    n, h, w = labels.semantic.shape
    if model.wh != (w, h):
        raise ValueError(f"labels are {w}x{h} but the model renders {model.wh[0]}x{model.wh[1]}")
    train = np.flatnonzero(is_train)
    things_all = np.isin(labels.semantic, cfg.thing_classes) & (labels.instance > 0)
    train = train[[labels.semantic[i].__ne__(VOID).any() for i in train]]
    skip_instances = cfg.instances and len(train) > 0 and not things_all[train].any()
    if skip_instances:  # no fruit detected in the window: nothing to assign, no instance head to train
        cfg = replace(cfg, instances=False, steps=min(cfg.steps, cfg.stuff_only_steps))
    k_np = model.intrinsics.cpu().numpy()
    window, n_slots = slot_window_for(labels, is_train, depths, k_np, cfg)
    pfield = panoptic_field(model, cfg, n_slots).to(dev)
    params = [{"params": list(pfield.semantic.parameters()) + list(pfield.instance.parameters()), "lr": cfg.lr_mlp}]
    if pfield.grid is not None:
        params.append({"params": list(pfield.grid.parameters()), "lr": cfg.lr_grid, "eps": 1e-15})
    shared = cfg.grid_mode == "shared"
    if shared:  # one grid for colour and panoptic: the panoptic losses move the colour grid too
        params.append({"params": model.field.feature_parameters(), "lr": cfg.lr_grid * 0.1, "eps": 1e-15})
    opt = torch.optim.Adam(params)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda s: 0.1 ** min(1.0, s / max(cfg.steps, 1)))
    rng = np.random.default_rng(seed)
    n_params = param_count(pfield) - (0 if cfg.instances else param_count(pfield.instance))
    result = PanopticResult(pfield, cfg, window if cfg.id_window and cfg.instances else None, n_slots, 0, 0.0, n_params)
    result.instances_skipped = skip_instances
    if len(train) == 0:  # nothing labelled: heads stay untrained, renders say stuff/uniform
        result.fit_s = time.perf_counter() - t0
        return result
    cams = model.poses_c2w[:, :3, 3].detach().cpu().numpy()
    memory = SlotMemory(n_slots)
    sem_t = torch.from_numpy(labels.semantic)
    inst_t = torch.from_numpy(labels.instance)
    conf_t = torch.from_numpy(labels.confidence)
    margin = int(round(cfg.stuff_border * min(h, w)))
    near_border = torch.zeros(h, w, dtype=torch.bool)
    if margin > 0:
        near_border[:margin] = near_border[-margin:] = True
        near_border[:, :margin] = near_border[:, -margin:] = True
    for step in range(cfg.steps):
        frames = rng.choice(train, size=min(cfg.frames_per_step, len(train)), replace=False)
        draws = [_draw_pixels(labels.semantic[i], things_all[i], cfg.rays_per_frame, cfg.thing_ray_share, rng)
                 for i in frames]
        fi = torch.from_numpy(np.repeat(frames, [len(p) for p, _ in draws])).long()
        flat = torch.from_numpy(np.concatenate([p for p, _ in draws])).long()
        importance = torch.from_numpy(np.concatenate([q for _, q in draws])).float().to(dev)
        v, u = flat // w, flat % w
        o, d = pixel_rays(model.intrinsics[fi.to(dev)], model.poses_c2w[fi.to(dev)],
                          u.float().to(dev) + 0.5, v.float().to(dev) + 0.5)
        ks = weighted_samples(model, o, d, cfg.min_weight, keep_grad_features=shared)
        p_sem, p_inst = ray_probs(pfield, ks)
        sem = sem_t[fi, v, u].to(dev).long()
        inst = inst_t[fi, v, u].to(dev).long()
        conf = conf_t[fi, v, u].to(dev)
        is_thing = torch.zeros_like(sem, dtype=torch.bool)
        for c in cfg.thing_classes:
            is_thing |= sem == c
        is_thing &= inst > 0
        is_stuff = (sem != VOID) & ~torch.isin(sem, torch.tensor(cfg.thing_classes, device=dev))
        if margin > 0:  # untrusted stuff labels near the border: void
            edge = near_border[v, u].to(dev) & is_stuff
            sem = torch.where(edge, torch.full_like(sem, VOID), sem)
            is_stuff &= ~edge
        target = torch.full_like(sem, -1)
        target[is_stuff] = 0
        seg_index = torch.full_like(sem, -1)
        n_seg_total = 0
        pts = (o + d * ks.depth[:, None]).detach().cpu().numpy()
        for j, i in enumerate(frames if cfg.instances else []):
            rows = torch.nonzero((fi == int(i)).to(dev) & is_thing).squeeze(1)
            if rows.numel() == 0:
                result.frames_without_things += 1
                continue  # a frame without fruit needs no assignment
            t_assign = time.perf_counter()
            ids, local = torch.unique(inst[rows], return_inverse=True)
            cost = segment_costs(p_inst[rows].detach(), local, len(ids)).cpu().numpy()
            centres, sizes = segment_geometry(pts[rows.cpu().numpy()], local.cpu().numpy(), len(ids))
            allowed = None
            if cfg.id_window:
                along = along_track(np.nan_to_num(centres), cams)
                allowed = window.allowed(along)
                cost = cost + cfg.position_prior * position_preference(window, along)
            if cfg.memory_prior > 0:
                cost = cost + cfg.memory_prior * memory.cost(np.nan_to_num(centres, nan=np.inf), sizes)
            slots = assign(cost, allowed)
            memory.update(slots, centres)
            result.assign_s += time.perf_counter() - t_assign
            result.frames_assigned += 1
            result.assignments += len(ids)
            result.overflow_segments += max(0, len(ids) - (n_slots - 1))
            target[rows] = torch.from_numpy(slots).to(dev)[local]
            seg_index[rows] = local + n_seg_total
            n_seg_total += len(ids)
        conf = torch.where(is_stuff, conf * cfg.stuff_confidence, conf)
        l_sem = semantic_loss(p_sem, sem, conf * importance, void=VOID)
        if cfg.instances:
            l_inst = instance_loss(p_inst, torch.where(is_thing, target, torch.full_like(target, -1)))
            l_stuff = instance_loss(p_inst, torch.where(is_stuff, target, torch.full_like(target, -1)))
            l_cons = consistency_loss(p_inst, seg_index, n_seg_total)
        else:
            l_inst = l_stuff = l_cons = torch.zeros((), device=dev)
        loss = cfg.w_semantic * l_sem + cfg.w_instance * l_inst + cfg.w_stuff * l_stuff + cfg.w_consistency * l_cons
        if not torch.isfinite(loss):
            from nerf.trainer import NonFiniteLoss
            raise NonFiniteLoss(f"non-finite panoptic loss ({float(loss.detach())}) at panoptic step {step}")
        opt.zero_grad(set_to_none=True)
        if loss.requires_grad:
            loss.backward()
            opt.step()
        sched.step()
        if step % 25 == 0 or step == cfg.steps - 1:
            rec = {"step": step, "loss": float(loss.detach()), "semantic": float(l_sem.detach()),
                   "instance": float(l_inst.detach()), "stuff": float(l_stuff.detach()),
                   "consistency": float(l_cons.detach()), "samples_per_ray": len(ks.w) / max(ks.n_rays, 1)}
            result.history.append(rec)
            if progress:
                progress(step + 1, cfg.steps, {"loss": rec["loss"]})
    result.steps = cfg.steps
    result.slot_centres = np.where((memory.count > 0)[:, None], memory.centre, np.nan)
    result.slot_centres[0] = np.nan
    result.fit_s = time.perf_counter() - t0
    return result


@torch.no_grad()
def render_panoptic(model, pres: PanopticResult, i: int | None = None, c2w: Tensor | None = None,
                    k: Tensor | None = None, chunk: int = 8192) -> dict:
    """Render frame i (or a given pose): rgb [H, W, 3], depth [H, W] (m), opacity, semantic [H, W] uint8,
    instance [H, W] int32 (window slots, 0 = stuff), after post-processing; samples_per_ray."""
    w, h = model.wh
    c2w, k, u, v = model.image_pixels(i, c2w, k)
    cfg = pres.cfg
    rgb, depth, opac, p_sem, p_inst = [], [], [], [], []
    n_eval = 0
    for s in range(0, u.shape[0], chunk):
        uu, vv = u[s:s + chunk], v[s:s + chunk]
        o, d = pixel_rays(k.expand(uu.shape[0], 4), c2w.expand(uu.shape[0], 4, 4), uu, vv)
        ks = weighted_samples(model, o, d, cfg.min_weight)
        ps, pi = ray_probs(pres.field, ks)
        rgb.append(ks.rgb)
        depth.append(ks.depth)
        opac.append(ks.opacity)
        p_sem.append(ps)
        p_inst.append(pi)
        n_eval += ks.n_evaluated
    p_sem_img = torch.cat(p_sem).reshape(h, w, -1).cpu().numpy()
    p_inst_img = torch.cat(p_inst).reshape(h, w, -1).cpu().numpy()
    depth_img = torch.cat(depth).reshape(h, w)
    points = None
    if cfg.region_reach_m > 0 or (pres.slot_centres is not None and cfg.slot_reach_m > 0):
        o, d = pixel_rays(k.expand(u.shape[0], 4), c2w.expand(u.shape[0], 4, 4), u, v)
        points = (o + d * depth_img.reshape(-1, 1)).reshape(h, w, 3).cpu().numpy()
    sem, inst = panoptic_labels(p_sem_img, p_inst_img, cfg, depth_img.cpu().numpy(), points, pres.slot_centres)
    return {"rgb": torch.cat(rgb).reshape(h, w, 3), "depth": depth_img,
            "opacity": torch.cat(opac).reshape(h, w), "semantic": sem, "instance": inst,
            "samples_per_ray": n_eval / (h * w)}


def panoptic_labels(p_sem: np.ndarray, p_inst: np.ndarray, cfg: PanopticConfig, depth: np.ndarray | None = None,
                    points: np.ndarray | None = None, slot_centres: np.ndarray | None = None
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel distributions [H, W, D] / [H, W, N] -> semantic uint8 and instance int32 images.

    A pixel is a thing when the fruit classes together are more likely than each stuff class (the
    ripeness classes split a fruit's probability three ways, so a plain argmax over the five classes
    calls a fruit of uncertain ripeness "plant"); it then takes the most likely thing class and the most
    likely thing slot (1..N-1). Instances grow into touching pixels of the same slot whose fruit
    probability exceeds cfg.grow_threshold (hysteresis) and, given the rendered `depth` [H, W], whose depth
    lies within cfg.grow_depth_m of the instance's sure pixels. Post-processing: each instance mask
    gets one 3x3 opening (erosion then dilation; the image border does not erode, so a fruit cut by it
    keeps its thin visible strip), instances smaller than cfg.min_segment_px are dropped,
    an instance's pixels take its majority thing class, and dropped pixels take their most likely
    stuff class with instance 0. With the pixels' world `points` [H, W, 3] and the slots' `slot_centres`
    [N, 3] (NaN = unplaced), a region too far from its slot's centre is handed to a slot placed near it
    (reach_slots)."""
    things = np.array(cfg.thing_classes, np.int64)
    stuff = np.array([c for c in range(p_sem.shape[-1]) if c not in set(cfg.thing_classes)], np.int64)
    stuff_sem = stuff[p_sem[..., stuff].argmax(-1)] if stuff.size else np.zeros(p_sem.shape[:-1], np.int64)
    best_thing = things[p_sem[..., things].argmax(-1)] if things.size else stuff_sem
    p_fruit = p_sem[..., things].sum(-1)                                   # 0 without thing classes
    is_thing = (p_fruit >= (p_sem[..., stuff].max(-1) if stuff.size else 0.0)) & (things.size > 0)
    slot = p_inst[..., 1:].argmax(-1) + 1
    if cfg.instances and things.size and cfg.grow_threshold < 1.0:
        is_thing = grow_instances(is_thing, slot, p_fruit > cfg.grow_threshold, depth, cfg.grow_depth_m)
    sem = np.where(is_thing, best_thing, stuff_sem)
    if not cfg.instances:  # semantic only: thing pixels keep their class, no instance ids
        return sem.astype(np.uint8), np.zeros(sem.shape, np.int32)
    inst = np.where(is_thing, slot, 0).astype(np.int32)
    if points is not None and cfg.region_reach_m > 0:
        inst = split_far_regions(inst, p_inst, points, cfg.region_reach_m)
    if points is not None and slot_centres is not None and cfg.slot_reach_m > 0:
        inst = reach_slots(inst, p_inst, points, slot_centres, cfg.slot_reach_m)
    out_sem = sem.astype(np.uint8)
    out_inst = np.zeros_like(inst)
    kernel = np.ones((3, 3), bool)
    for sl_id in np.unique(inst[inst > 0]):
        mask = inst == sl_id
        opened = ndimage.binary_dilation(ndimage.binary_erosion(mask, kernel, border_value=1), kernel) & mask
        if opened.sum() < cfg.min_segment_px:
            continue
        classes, counts = np.unique(sem[opened], return_counts=True)
        thing_counts = [(n_, c) for c, n_ in zip(classes, counts) if c in set(cfg.thing_classes)]
        out_sem[opened] = max(thing_counts)[1] if thing_counts else out_sem[opened]
        out_inst[opened] = sl_id
    dropped = is_thing & (out_inst == 0)
    out_sem[dropped] = stuff_sem[dropped]
    return out_sem, out_inst


def slot_regions(inst: np.ndarray, points: np.ndarray) -> dict[int, list[tuple[np.ndarray, np.ndarray]]]:
    """{slot: [(mask [H, W], 3D centre [3])]} of the 8-connected regions of each slot of the instance image
    [H, W] (0 = none), largest first; centre = median of the region's finite `points` [H, W, 3] (NaN if none)."""
    eight = np.ones((3, 3), bool)
    out = {}
    for sl_id in np.unique(inst[inst > 0]):
        lab, n = ndimage.label(inst == sl_id, eight)
        found = []
        for r in range(1, n + 1):
            m = lab == r
            pts = points[m]
            pts = pts[np.isfinite(pts).all(1)]
            found.append((m, np.median(pts, 0) if len(pts) else np.full(3, np.nan)))
        out[int(sl_id)] = sorted(found, key=lambda x: -int(x[0].sum()))
    return out


def split_far_regions(inst: np.ndarray, p_inst: np.ndarray, points: np.ndarray, reach_m: float) -> np.ndarray:
    """Instance image [H, W] (slots, 0 = none) with every 8-connected region of a slot whose 3D centre (median
    of its pixels' `points` [H, W, 3]) lies farther than reach_m from the centre of that slot's largest
    region in the frame relabelled to the slot whose largest region lies within reach_m of it with the
    largest summed probability `p_inst` [H, W, N] over the region; kept when no such slot exists."""
    regions = slot_regions(inst, points)
    main = {sl: rs[0][1] for sl, rs in regions.items()}
    out = inst.copy()
    for sl, rs in regions.items():
        for m, c in rs[1:]:
            if not (np.isfinite(c).all() and np.isfinite(main[sl]).all()) or np.linalg.norm(c - main[sl]) <= reach_m:
                continue
            near = [o for o, oc in main.items() if o != sl and np.isfinite(oc).all() and np.linalg.norm(c - oc) <= reach_m]
            if near:
                out[m] = near[int(np.argmax(p_inst[m][:, near].sum(0)))]
    return out


def reach_slots(inst: np.ndarray, p_inst: np.ndarray, points: np.ndarray, centres: np.ndarray,
                reach_m: float) -> np.ndarray:
    """Instance image [H, W] (slots, 0 = none) with every 8-connected region of one slot whose 3D centre
    (median of its pixels' `points` [H, W, 3]) lies farther than reach_m from the slot's placed centre
    (`centres` [N, 3], NaN = never placed) relabelled to the slot placed within reach_m of the region with
    the largest summed probability `p_inst` [H, W, N] over it; kept as it is when no slot is placed there.
    Regions of unplaced slots are kept too."""
    out = inst.copy()
    placed = np.isfinite(centres).all(1)
    for sl_id, rs in slot_regions(inst, points).items():
        if not placed[sl_id]:
            continue
        for m, c in rs:
            if not np.isfinite(c).all():
                continue
            dist = np.where(placed, np.linalg.norm(np.nan_to_num(centres) - c, axis=1), np.inf)
            if dist[sl_id] <= reach_m:
                continue
            near = np.flatnonzero(dist <= reach_m)
            if len(near):
                out[m] = near[np.argmax(p_inst[m][:, near].sum(0))]
    return out


def instance_spheres(frames: list[tuple[np.ndarray, np.ndarray]], intrinsics: np.ndarray, c2w: np.ndarray,
                     cfg: PanopticConfig, max_per_frame: int = 400) -> dict[int, tuple[np.ndarray, float]]:
    """{instance id: (sphere centre [3], radius)} of the instances of a window's rendered frames
    (`frames` = [(instance [H, W], depth [H, W] metres)], with `intrinsics` [N, 4] fx fy cx cy and `c2w`
    [N, 4, 4] per frame) whose pixels, un-projected with the depth, fit a plausible fruit sphere
    (nerf.surfaces.plausible_fit, radius <= cfg.complete_max_radius_m). A fruit seen only as a shallow cap
    gets none (tried: a sphere of half the cap's extent behind it claimed leaves and fixed no fruit)."""
    pts: dict[int, list[np.ndarray]] = {}
    rng = np.random.default_rng(0)
    for (inst, depth), k, pose in zip(frames, intrinsics, c2w):
        for sl_id in np.unique(inst[inst > 0]):
            v, u = np.nonzero((inst == sl_id) & (depth > 0))
            if len(v) > max_per_frame:
                pick = rng.choice(len(v), max_per_frame, replace=False)
                v, u = v[pick], u[pick]
            pts.setdefault(int(sl_id), []).append(unproject(depth, k, pose, v, u))
    out = {}
    for sl_id, chunks in pts.items():
        p = np.concatenate(chunks)
        if len(p) < cfg.complete_min_points:
            continue
        med, keep = robust_centre(p)
        c, r = fit_sphere(p[keep])
        if plausible_fit(c, r, med, principal_extents(p[keep])[0], cfg.complete_max_radius_m, 2.0):
            out[sl_id] = (c, r)
    return out


def complete_instances(frames: list[dict], intrinsics: np.ndarray, c2w: np.ndarray, cfg: PanopticConfig) -> int:
    """3D instance completion over a window's rendered frames (dicts with 'semantic' [H, W] uint8, 'instance'
    [H, W] int32, 'depth' [H, W] metres, numpy or torch; changed in place): every stuff pixel whose
    un-projected point lies inside an instance's sphere (instance_spheres, radius + cfg.complete_margin_m)
    joins that instance with its majority class; a pixel inside two spheres goes to the one it lies deeper
    in (smaller distance / radius). Pixels of other instances are never taken. Returns the pixels added
    (0 with cfg.complete_3d off)."""
    if not (cfg.complete_3d and cfg.instances and frames):
        return 0
    as_np = lambda a: a.detach().cpu().numpy() if isinstance(a, Tensor) else np.asarray(a)  # noqa: E731
    depths = [as_np(f["depth"]).astype(np.float64) for f in frames]
    spheres = instance_spheres([(f["instance"], d) for f, d in zip(frames, depths)], intrinsics, c2w, cfg)
    if not spheres:
        return 0
    klass = {}
    for sl_id in spheres:
        cls = np.concatenate([f["semantic"][f["instance"] == sl_id] for f in frames])
        vals, n = np.unique(cls, return_counts=True)
        klass[sl_id] = int(vals[np.argmax(n)])
    ids = np.array(list(spheres))
    centres = np.stack([spheres[i][0] for i in ids])                    # [S, 3]
    radii = np.array([spheres[i][1] for i in ids])                      # [S]
    added = 0
    for f, depth, k, pose in zip(frames, depths, intrinsics, c2w):
        v, u = np.nonzero((f["instance"] == 0) & (depth > 0))
        if not len(v):
            continue
        p = unproject(depth, k, pose, v, u)                             # [P, 3]
        rel = np.linalg.norm(p[:, None] - centres[None], axis=2)        # [P, S]
        inside = rel <= radii + cfg.complete_margin_m
        score = np.where(inside, rel / radii, np.inf)
        if cfg.complete_core > 0:
            through, closest = rays_through_core(depth, k, pose, v, u, centres, radii * cfg.complete_core,
                                                 cfg.complete_margin_m)
            inside |= through
            score = np.minimum(score, np.where(through, closest / radii, np.inf))
        hit = inside.any(1)
        if not hit.any():
            continue
        best = score.argmin(1)
        vv, uu, who = v[hit], u[hit], ids[best[hit]]
        f["instance"][vv, uu] = who
        f["semantic"][vv, uu] = [klass[int(i)] for i in who]
        added += int(hit.sum())
    return added


def rays_through_core(depth: np.ndarray, k: np.ndarray, c2w: np.ndarray, v: np.ndarray, u: np.ndarray,
                      centres: np.ndarray, core_radii: np.ndarray, margin_m: float) -> tuple[np.ndarray, np.ndarray]:
    """For pixels (v, u) of a frame with rendered z-depth `depth`, intrinsics k = (fx, fy, cx, cy) and pose
    c2w, and spheres (centres [S, 3], core_radii [S]): ([P, S] bool: the pixel's ray passes within the
    sphere in front of the camera and its rendered depth is not in front of the ray's entry into it by more
    than margin_m, [P, S] the ray's closest distance to each centre)."""
    d = unproject(np.ones_like(depth), k, c2w, v, u) - c2w[:3, 3]      # world rays with camera z = 1
    norm = np.linalg.norm(d, axis=1)                                    # ray length per unit of z-depth
    oc = centres - c2w[:3, 3]                                           # [S, 3]
    along = (d / norm[:, None]) @ oc.T                                  # [P, S] ray length to the closest point
    dist2 = np.maximum((oc ** 2).sum(1)[None] - along ** 2, 0.0)
    entry_z = (along - np.sqrt(np.maximum(core_radii[None] ** 2 - dist2, 0.0))) / norm[:, None]
    through = (dist2 <= core_radii[None] ** 2) & (along > 0) & (depth[v, u][:, None] >= entry_z - margin_m)
    return through, np.sqrt(dist2)


def grow_instances(sure: np.ndarray, slot: np.ndarray, weak: np.ndarray, depth: np.ndarray | None = None,
                   depth_margin_m: float = 0.0) -> np.ndarray:
    """Hysteresis: `sure` [H, W] plus every 8-connected region of `weak` pixels of one slot that touches a
    sure pixel of that slot. With `depth`, a weak pixel must also lie within `depth_margin_m` of the depth
    range (5th-95th percentile) of the slot's sure pixels: a fruit's rim, not the leaf or the wall behind."""
    out = sure.copy()
    eight = np.ones((3, 3), bool)
    for sl_id in np.unique(slot[sure]):
        core = sure & (slot == sl_id)
        cand = weak & (slot == sl_id)
        if depth is not None:
            lo, hi = np.percentile(depth[core], [5, 95])
            cand &= (depth >= lo - depth_margin_m) & (depth <= hi + depth_margin_m)
        regions, n = ndimage.label(cand | core, eight)
        if n:
            touching = np.unique(regions[core])
            out |= np.isin(regions, touching[touching > 0])
    return out


def load_panoptic(state: dict, model, device: str = "cpu") -> PanopticResult:
    """PanopticResult (field and settings only) from PanopticResult.state()."""
    cfg = PanopticConfig(**{**state["cfg"], "thing_classes": tuple(state["cfg"]["thing_classes"])})
    pfield = panoptic_field(model, cfg, state["n_slots"]).to(device)
    pfield.load_state_dict(state["field"])
    sw = SlotWindow(**state["slot_window"]) if state.get("slot_window") else None
    centres = state.get("slot_centres")
    return PanopticResult(pfield, cfg, sw, state["n_slots"], 0, 0.0, param_count(pfield),
                          slot_centres=None if centres is None else np.asarray(centres, np.float64))

