"""The numerical stress cases: the model pieces under extreme but possible inputs.

Every case feeds one kind of extreme input through the library and checks that the outputs (and, where
something trains through them, the gradients) are finite and valid, or that the input is refused with a
clear error, and that the pure-torch reference and the fused encoding kernel agree wherever both apply.
A case is a function (n, device) -> Checks; test_numerical_stress.py runs each as a parametrised pytest
case at the fast size, `pag bench stress` (bench/stress.py) runs the same functions at either size and
writes their checks as a table.
"""
from __future__ import annotations

import math
import re
import warnings
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from nerf.panoptic.assignment import OUTSIDE_COST, SlotWindow, assign, segment_costs
from nerf.config import preset
from nerf.encoding import PermutoEncoding, simplex
from nerf.fields import RadianceField
from nerf.occupancy import OccupancyGrid
from nerf.panoptic.heads import integrate_probs
from nerf.panoptic.losses import consistency_loss, instance_loss, semantic_loss
from nerf.panoptic_metrics import PanopticAccumulator
from nerf.poses import PoseCorrection, rotation_6d
from nerf.render import accumulate, composite_weights, cone_steps, march, pixel_rays

SIZES = {"fast": 512, "full": 65536}
"""points (or rays) per case."""


@dataclass
class Check:
    component: str
    passed: bool
    detail: str


class Checks(list):
    """The checks of one case, in order."""

    def add(self, component: str, passed: bool, detail: str = "") -> bool:
        self.append(Check(component, bool(passed), detail))
        return bool(passed)

    def finite(self, component: str, **tensors: Tensor | None) -> bool:
        bad = [k for k, t in tensors.items() if t is not None and not bool(torch.isfinite(t).all())]
        return self.add(component, not bad, f"non-finite: {bad}" if bad else "finite")

    def close(self, component: str, a: Tensor, b: Tensor, atol: float, rtol: float = 0.0) -> bool:
        err = float((a.double() - b.double()).abs().max()) if a.numel() else 0.0
        scale = float(b.double().abs().max()) if b.numel() else 0.0
        return self.add(component, err <= atol + rtol * scale, f"max abs diff {err:.3g} (atol {atol:g}, rtol {rtol:g})")

    def raises(self, component: str, fn: Callable[[], object], exc: type[BaseException], match: str) -> bool:
        try:
            fn()
        except exc as err:
            ok = re.search(match, str(err)) is not None
            return self.add(component, ok, f"{type(err).__name__}: {err}" if ok else f"unclear message: {err}")
        except Exception as err:  # noqa: BLE001 - any other error is the failure being reported
            return self.add(component, False, f"expected {exc.__name__}, got {type(err).__name__}: {err}")
        return self.add(component, False, f"accepted invalid input, expected {exc.__name__}")


def _fused_available(device: str) -> bool:
    from nerf._ext import load_permuto_ext

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return load_permuto_ext(torch.device(device).type) is not None


def _encoding_pair(device: str, n_levels: int = 6, log2_capacity: int = 12) -> dict[str, PermutoEncoding]:
    """The same encoding (same table) on the reference path and, when it builds, on the fused kernel."""
    ref = PermutoEncoding(n_levels=n_levels, log2_capacity=log2_capacity, coarsest_scale=1.0, finest_scale=0.01,
                          backend="torch", init_std=0.1).to(device)
    out = {"torch": ref}
    if _fused_available(device):
        fused = PermutoEncoding(n_levels=n_levels, log2_capacity=log2_capacity, coarsest_scale=1.0, finest_scale=0.01,
                                backend="fused", init_std=0.1).to(device)
        fused.load_state_dict(ref.state_dict())
        out["fused"] = fused
    return out


def _encode_with_grads(enc: PermutoEncoding, x: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """(features, d sum(features * probe) / d x, ... / d table) for a fixed random probe."""
    x = x.detach().clone().requires_grad_(True)
    enc.table.grad = None
    f = enc(x)
    probe = torch.linspace(-1, 1, f.shape[1], device=f.device)
    (f * probe).sum().backward()
    return f.detach(), x.grad.detach(), enc.table.grad.detach()


def _at_kink(enc: PermutoEncoding, x: Tensor, eps: float = 1e-5) -> Tensor:
    """[N] True where a point lies within eps of a simplex boundary at some level: the encoding is
    continuous there but d/dx jumps, and either one-sided derivative is right."""
    xs = enc.bound
    x = torch.nan_to_num(x.detach().float(), nan=0.0, posinf=xs, neginf=-xs).clamp(-xs, xs)
    _, keys, _ = simplex(x, enc.coef, enc.shifts)
    out = torch.zeros(x.shape[0], dtype=torch.bool, device=x.device)
    for axis in range(3):
        for sign in (-1.0, 1.0):
            step = torch.zeros(3, device=x.device)
            step[axis] = sign * eps * max(1.0, float(x.abs().max()) * 1e-6)
            _, k1, _ = simplex(x + step, enc.coef, enc.shifts)
            out |= (k1 != keys).flatten(2).any(-1).any(0)
    return out


def _compare_backends(checks: Checks, tag: str, encs: dict[str, PermutoEncoding], x: Tensor) -> None:
    outs = {k: _encode_with_grads(e, x) for k, e in encs.items()}
    for k, (f, gx, gt) in outs.items():
        checks.finite(f"encoding[{tag},{k}]", features=f, grad_x=gx, grad_table=gt)
    if "fused" in outs:
        (f0, gx0, gt0), (f1, gx1, gt1) = outs["torch"], outs["fused"]
        checks.close(f"encoding[{tag}] fused vs reference: features", f1, f0, atol=1e-5)
        checks.close(f"encoding[{tag}] fused vs reference: d/dtable", gt1, gt0, atol=1e-4, rtol=1e-4)
        # d/dx comes back in x's dtype (bfloat16: 3 significant digits), and jumps at simplex boundaries
        smooth = ~_at_kink(encs["torch"], x)
        rtol = max(1e-3, 2 * torch.finfo(x.dtype).eps)
        checks.close(f"encoding[{tag}] fused vs reference: d/dx", gx1[smooth], gx0[smooth], atol=1e-3, rtol=rtol)
        checks[-1].detail += f"; {int((~smooth).sum())} of {len(x)} points on simplex boundaries left out"
    else:
        checks.add(f"encoding[{tag}] fused vs reference", True, "skipped: fused kernel unavailable on this device")


def _packed(n_rays: int, per_ray: int, device: str) -> Tensor:
    return torch.arange(n_rays, device=device).repeat_interleave(per_ray)


# -- cases ------------------------------------------------------------------------------------------
def case_autocast(n: int, device: str) -> Checks:
    """float16 / bfloat16 autocast through encoding -> field -> compositing, forward and backward."""
    checks = Checks()
    cfg = preset("cpu", n_levels=6, log2_capacity=12)
    g = torch.Generator().manual_seed(0)
    x = (torch.rand(n, 3, generator=g) * 2 - 1).to(device)
    d = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1).to(device)
    per_ray = 8
    n_rays = n // per_ray
    ray_index = _packed(n_rays, per_ray, device)
    delta = torch.full((n_rays * per_ray,), 0.01, device=device)
    backends = ["torch"] + (["fused"] if _fused_available(device) else [])
    dtypes = [torch.bfloat16, torch.float16]
    for backend in backends:
        fld = RadianceField(cfg, 1.0).to(device)
        fld.grid.backend = backend
        with torch.no_grad():  # a saturated density head: exp(15) = 3.3e6 overflows float16
            fld.density_net[-1].bias[0] = 25.0
        results = {}
        for dt in [None, *dtypes]:
            fld.zero_grad(set_to_none=True)
            with torch.autocast(device_type=torch.device(device).type, dtype=dt or torch.float32, enabled=dt is not None):
                sigma, rgb, feat = fld(x[: n_rays * per_ray], d[: n_rays * per_ray])
                w, left = composite_weights(sigma, delta, ray_index, n_rays)
                col = accumulate(rgb, w, ray_index, n_rays)
                loss = (col.float() - 0.5).pow(2).mean() + left.float().mean()
            loss.backward()
            name = str(dt).replace("torch.", "") if dt else "float32"
            results[name] = col.detach().float()
            checks.finite(f"encoding+field+render[{name},{backend}]", sigma=sigma, rgb=rgb, weights=w, colour=col,
                          loss=loss.detach(), grad_table=fld.grid.table.grad,
                          grad_mlp=torch.cat([p.grad.flatten().float() for p in fld.density_net.parameters()]))
            sums = torch.zeros(n_rays, device=device).index_add_(0, ray_index, w.float())
            checks.add(f"encoding+field+render[{name},{backend}] weights sum <= 1", bool((sums <= 1 + 1e-3).all()),
                       f"max per-ray weight sum {float(sums.detach().max()):.6f}")
        for name in ("bfloat16", "float16"):
            checks.close(f"encoding+field+render[{name},{backend}] vs float32 colour", results[name],
                         results["float32"], atol=0.05)
    encs = _encoding_pair(device)
    for dt in dtypes:  # the encoding computes in float32 whatever the autocast state
        with torch.autocast(device_type=torch.device(device).type, dtype=dt):
            _compare_backends(checks, str(dt).replace("torch.", ""), encs, x.to(dt))
    return checks


def case_densities(n: int, device: str) -> Checks:
    """Huge, tiny, zero and infinite densities (and zero-length intervals) through compositing."""
    checks = Checks()
    g = torch.Generator().manual_seed(1)
    per_ray = 16
    n_rays = max(n // per_ray, 8)
    ray_index = _packed(n_rays, per_ray, device)
    log_sigma = torch.empty(n_rays * per_ray).uniform_(-30, 30, generator=g)
    sigma = (10.0 ** log_sigma).to(device)
    special = torch.tensor([0.0, 1e-30, 1e-6, 1.0, 3.3e6, 1e30, 3.4e38, math.inf], device=device)
    sigma[: len(special) * per_ray] = special.repeat_interleave(per_ray)
    delta = torch.empty(n_rays * per_ray).uniform_(0, 0.05, generator=g).to(device)
    delta[::7] = 0.0  # empty intervals, also under infinite densities
    for name, s in (("random 1e-30..1e30", sigma), ("all huge (3.4e38)", torch.full_like(sigma, 3.4e38)),
                    ("all tiny (1e-38)", torch.full_like(sigma, 1e-38)), ("all zero", torch.zeros_like(sigma))):
        s = s.clone().requires_grad_(True)
        w, left = composite_weights(s, delta, ray_index, n_rays)
        vals = torch.rand(len(w), 3, generator=g).to(device)
        col = accumulate(vals, w, ray_index, n_rays)
        (col.sum() + left.sum()).backward()
        checks.finite(f"composite[{name}]", weights=w, transmittance=left, colour=col, grad_sigma=s.grad)
        sums = torch.zeros(n_rays, device=device, dtype=w.dtype).index_add_(0, ray_index, w.detach())
        checks.add(f"composite[{name}] 0 <= weights, sum <= 1", bool((w >= 0).all() and (sums <= 1 + 1e-6).all()),
                   f"min weight {float(w.detach().min()):.3g}, max per-ray sum {float(sums.max()):.9f}")
        checks.close(f"composite[{name}] sum + transmittance = 1", sums + left.detach(), torch.ones_like(sums), atol=1e-5)
    # a ray's weights must not depend on the rays packed before it (float32 cancellation)
    thin = torch.full((per_ray,), 1.0, device=device)
    alone, _ = composite_weights(thin, torch.full_like(thin, 0.05), torch.zeros(per_ray, dtype=torch.long, device=device), 1)
    opaque = torch.full(((n_rays - 1) * per_ray,), 3.3e6, device=device)
    w, _ = composite_weights(torch.cat([opaque, thin]), torch.full(((n_rays) * per_ray,), 0.05, device=device),
                             ray_index, n_rays)
    checks.close("composite: a thin ray after many opaque ones = the ray alone", w[-per_ray:], alone, atol=1e-6)
    return checks


def case_near_far(n: int, device: str) -> Checks:
    """Near and far planes touching; invalid planes are refused."""
    checks = Checks()
    edges = cone_steps(0.5, 0.5, 0.01, torch.device(device))
    checks.add("cone_steps[near = far]", edges.numel() == 1, f"edges {edges.tolist()}")
    n_rays = max(n // 16, 4)
    o = torch.zeros(n_rays, 3, device=device)
    d = torch.nn.functional.normalize(torch.randn(n_rays, 3), dim=-1).to(device)
    s = march(o, d, edges, lambda p: torch.ones(p.shape[0], dtype=torch.bool, device=p.device), jitter=True)
    w, left = composite_weights(torch.ones(len(s), device=device), s.delta, s.ray_index, n_rays)
    col = accumulate(torch.ones(len(s), 3, device=device), w, s.ray_index, n_rays)
    checks.add("march+composite[near = far] no samples, nothing rendered", len(s) == 0 and bool((left == 1).all())
               and bool((col == 0).all()), f"{len(s)} samples")
    for near, far in ((0.0, 2.0), (-0.1, 2.0), (1.0, 0.5), (0.1, math.inf), (math.nan, 1.0)):
        checks.raises(f"cone_steps[near={near}, far={far}] refused", lambda: cone_steps(near, far, 0.01, torch.device(device)),
                      ValueError, "near")
    checks.raises("cone_steps[step 0] refused", lambda: cone_steps(0.1, 1.0, 0.0, torch.device(device)), ValueError, "step")
    return checks


def case_axis_parallel(n: int, device: str) -> Checks:
    """Rays (and points) parallel to a lattice axis and on lattice planes: ties in the simplex ranks."""
    checks = Checks()
    encs = _encoding_pair(device)
    t = torch.linspace(-1, 1, n, device=device)[:, None]
    z = torch.zeros_like(t)
    lines = {"x axis": torch.cat([t, z, z], 1), "y axis": torch.cat([z, t, z], 1), "z axis": torch.cat([z, z, t], 1),
             "diagonal (1,1,1)": torch.cat([t, t, t], 1),
             "on a lattice plane": torch.cat([t, torch.full_like(t, 0.25), torch.full_like(t, 0.5)], 1)}
    enc = encs["torch"]
    for name, x in lines.items():
        _compare_backends(checks, name, encs, x)
        _, _, w = simplex(x, enc.coef, enc.shifts)
        checks.add(f"simplex[{name}] barycentric weights >= 0, sum 1",
                   bool((w >= -1e-5).all()) and bool(((w.sum(-1) - 1).abs() < 1e-5).all()),
                   f"min {float(w.min()):.2e}, max |sum - 1| {float((w.sum(-1) - 1).abs().max()):.2e}")
    # camera rays exactly along the world axes (principal-point pixels of axis-aligned cameras)
    k = torch.tensor([[100.0, 100.0, 50.0, 50.0]], device=device)
    for axis, rot in (("z", torch.eye(3)), ("x", torch.tensor([[0.0, 0, 1], [0, 1, 0], [-1, 0, 0]]))):
        c2w = torch.eye(4, device=device)
        c2w[:3, :3] = rot
        o, d = pixel_rays(k, c2w[None], torch.tensor([50.0], device=device), torch.tensor([50.0], device=device))
        s = march(o, d, cone_steps(0.1, 2.0, 0.01, torch.device(device)),
                  lambda p: torch.ones(p.shape[0], dtype=torch.bool, device=p.device), jitter=False)
        x = o[s.ray_index] + d[s.ray_index] * s.t_mid[:, None]
        feats = enc(x)
        checks.finite(f"render ray along the {axis} axis", samples=x, features=feats)
    return checks


def case_far_outside(n: int, device: str) -> Checks:
    """Points far outside the grid bounds (and non-finite ones): encoding finite, kernels agree."""
    checks = Checks()
    encs = _encoding_pair(device)
    g = torch.Generator().manual_seed(2)
    base = torch.rand(n, 3, generator=g) * 2 - 1
    for name, scale in (("1e3", 1e3), ("1e8", 1e8), ("1e30", 1e30)):
        _compare_backends(checks, f"|x| ~ {name}", encs, (base * scale).to(device))
    special = torch.tensor([[math.inf, 0, 0], [-math.inf, 1, 2], [math.nan, 0.5, 0.5], [1e38, -1e38, 3.0]])
    x = torch.cat([special, base[: max(n - 4, 1)]]).to(device)
    _compare_backends(checks, "inf / nan / 1e38", encs, x)
    grid = OccupancyGrid(torch.tensor([-1.0, -1, -1]), torch.tensor([1.0, 1, 1]), 16, device)
    occ = grid.query(torch.cat([x, torch.tensor([[0.0, 0, 0]], device=device)]))
    checks.add("occupancy query outside the bounds is False", not bool(occ[:4].any()) and bool(occ[-1]),
               f"occupied flags of the special points {occ[:4].tolist()}")
    fld = RadianceField(preset("cpu", n_levels=4, log2_capacity=10), 1.0).to(device)
    checks.finite("field density far outside", sigma=fld.density(x))
    return checks


def case_rotation_6d(n: int, device: str) -> Checks:
    """Degenerate 6D rotation inputs give finite, orthonormal rotations with finite gradients."""
    checks = Checks()
    g = torch.Generator().manual_seed(3)
    a1 = torch.randn(n, 3, generator=g)
    special = {
        "zero": torch.zeros(6), "a1 zero": torch.tensor([0.0, 0, 0, 0, 1, 0]), "a2 zero": torch.tensor([1.0, 0, 0, 0, 0, 0]),
        "collinear": torch.tensor([1.0, 2, 3, 2, 4, 6]), "anti-parallel": torch.tensor([1.0, 0, 0, -3, 0, 0]),
        "nearly collinear": torch.tensor([1.0, 1, 0, 1, 1, 1e-9]), "huge (1e30)": torch.full((6,), 1e30),
        "tiny (1e-30)": torch.full((6,), 1e-30), "subnormal": torch.tensor([1e-40, 0, 0, 0, 1e-40, 0]),
        "non-finite": torch.tensor([math.nan, 0, 0, 0, math.inf, 0]),
    }
    a = torch.cat([torch.stack(list(special.values())), torch.cat([a1, a1 * 2.5], 1),    # a2 parallel to a1
                   torch.randn(n, 6, generator=g)]).to(device).requires_grad_(True)
    r = rotation_6d(a)
    r.sum().backward()
    checks.finite("rotation_6d", rotation=r, grad=a.grad)
    eye = torch.eye(3, device=device)
    r = r.detach()
    orth = (r.transpose(1, 2) @ r - eye).abs().amax((1, 2))
    det = torch.linalg.det(r)
    worst = int(orth.argmax())
    names = list(special) + [f"collinear random #{i}" for i in range(n)] + [f"random #{i}" for i in range(n)]
    checks.add("rotation_6d orthonormal, det +1", bool((orth < 1e-5).all() and ((det - 1).abs() < 1e-5).all()),
               f"max |R^T R - I| {float(orth.max()):.2e} ({names[worst]}), det in [{float(det.min()):.6f}, "
               f"{float(det.max()):.6f}]")
    pc = PoseCorrection(len(special), 1.0).to(device)
    with torch.no_grad():
        pc.rot6d.copy_(torch.stack(list(special.values())).to(device))
    c2w = pc.apply(torch.eye(4, device=device).repeat(len(special), 1, 1), torch.arange(len(special), device=device))
    c2w.sum().backward()
    checks.finite("PoseCorrection.apply with degenerate parameters", pose=c2w, grad=pc.rot6d.grad)
    return checks


def case_all_background(n: int, device: str) -> Checks:
    """Frames without a single thing segment: assignment, panoptic losses and PQ."""
    checks = Checks()
    n_slots = 9
    p = torch.softmax(torch.randn(n, n_slots), -1).to(device).requires_grad_(True)
    cost = segment_costs(p[:0], torch.zeros(0, dtype=torch.long, device=device), 0)  # no thing rays
    slots = assign(cost.detach().cpu().numpy())
    checks.add("assign with no segments", slots.shape == (0,), f"result shape {slots.shape}")
    loss = (instance_loss(p, torch.full((n,), -1, device=device)) + consistency_loss(p, torch.full((n,), -1, device=device), 0)
            + semantic_loss(p, torch.full((n,), 255, device=device), torch.ones(n, device=device)))
    loss.backward()
    checks.add("panoptic losses with no thing and no labelled ray", float(loss.detach()) == 0.0,
               f"loss {float(loss.detach())}")
    checks.finite("panoptic losses with no thing: gradient", grad=p.grad)
    probs = integrate_probs(torch.randn(n, 5, device=device), torch.zeros(n, device=device),
                            torch.arange(n, device=device) // 4, max(n // 4, 1))
    checks.close("integrate_probs on empty rays = uniform", probs, torch.full_like(probs, 0.2), atol=1e-6)
    acc = PanopticAccumulator(things={2, 3, 4}, stuff={0, 1})
    sem = np.zeros((12, 16), np.uint8)
    sem[:, 8:] = 1
    acc.update(sem, np.zeros_like(sem, np.int32), sem, np.zeros_like(sem, np.int32))
    res = acc.compute()
    checks.add("PQ of an all-background frame", res["pq"] == 1.0 and math.isnan(res["pq_things"]),
               f"pq {res['pq']}, pq_things {res['pq_things']}")
    return checks


def case_more_segments_than_slots(n: int, device: str) -> Checks:
    """More detected segments in one frame than instance slots: every segment still gets a valid slot."""
    checks = Checks()
    g = np.random.default_rng(4)
    n_slots = 9
    s = 3 * (n_slots - 1) + 2
    cost = -g.random((s, n_slots))
    slots = assign(cost)
    counts = np.bincount(slots, minlength=n_slots)
    checks.add("assign S > slots: valid slots", bool(((slots >= 1) & (slots < n_slots)).all()) and counts[0] == 0,
               f"slot use {counts.tolist()}")
    checks.add("assign S > slots: even reuse", counts[1:].max() <= math.ceil(s / (n_slots - 1)), f"slot use {counts.tolist()}")
    win = SlotWindow.for_scene(2, 0.5, 13, margin=1)
    allowed = win.allowed(g.random(s) * 2.0)
    slots = assign(-g.random((s, 13)), allowed)
    checks.add("assign S > slots with the sliding window: valid slots", bool(((slots >= 1) & (slots < 13)).all()),
               f"slots {slots.tolist()}")
    return checks


def case_equal_costs(n: int, device: str) -> Checks:
    """Cost matrices with equal (or all-outside, or non-finite) costs: deterministic, valid, distinct."""
    checks = Checks()
    for name, cost in (("all equal", np.full((5, 9), -0.5)), ("all zero", np.zeros((8, 9))),
                       ("all outside", np.full((4, 9), OUTSIDE_COST)),
                       ("nan / inf", np.where(np.eye(6, 9, dtype=bool), np.nan, np.inf))):
        a, b = assign(cost), assign(cost.copy())
        ok = (a == b).all() and ((a >= 1) & (a < 9)).all() and len(set(a.tolist())) == len(a)
        checks.add(f"assign[{name}] deterministic, valid, distinct", bool(ok), f"slots {a.tolist()}")
    allowed = np.zeros((5, 9), bool)
    a = assign(np.full((5, 9), -0.5), allowed)
    checks.add("assign[equal costs, nothing allowed] valid, distinct", bool(((a >= 1) & (a < 9)).all())
               and len(set(a.tolist())) == 5, f"slots {a.tolist()}")
    return checks


def case_nonfinite_inputs(n: int, device: str) -> Checks:
    """NaN / inf in sensor depth and detector confidence: skipped as documented, never propagated."""
    checks = Checks()
    g = torch.Generator().manual_seed(5)
    depth = torch.rand(n, generator=g) * 2 + 0.2
    depth[::5] = math.nan
    depth[1::5] = math.inf
    depth[2::5] = -math.inf
    d = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1)  # noqa: F841 (keeps the draws)
    from nerf.trainer import depth_supervised
    ok = depth_supervised(depth.reshape(1, 1, -1).to(device), 0.0, 3.5)[0, 0].cpu()
    checks.add("depth loss: pixels with NaN / inf depth carry none",
               not bool(ok[~torch.isfinite(depth)].any()) and bool(ok.any()), f"{int(ok.sum())} of {n} supervised")
    p = torch.softmax(torch.randn(n, 5, generator=g), -1).to(device).requires_grad_(True)
    conf = torch.rand(n, generator=g)
    conf[::3] = math.nan
    conf[1::3] = math.inf
    labels = torch.randint(0, 5, (n,), generator=g)
    loss = semantic_loss(p, labels.to(device), conf.to(device))
    slots = torch.randint(0, 5, (n,), generator=g).to(device)
    loss = loss + instance_loss(p, slots, conf.to(device))
    loss.backward()
    checks.finite("panoptic losses with NaN / inf confidence", loss=loss.detach(), grad=p.grad)
    probs = p.detach().clone()
    probs[:3] = math.nan
    cost = segment_costs(probs, torch.arange(n, device=device) % 4, 4).cpu().numpy()
    slots = assign(cost)
    checks.add("assignment with NaN probabilities: valid distinct slots",
               bool(((slots >= 1) & (slots < 5)).all()) and len(set(slots.tolist())) == 4, f"slots {slots.tolist()}")
    from nerf.window import WindowData

    poses = np.tile(np.eye(4), (2, 1, 1))
    poses[1, 0, 3] = np.nan
    checks.raises("WindowData with a NaN pose refused", lambda: WindowData(
        np.zeros((2, 4, 4, 3), np.uint8), np.zeros((2, 4, 4), np.float32), np.ones((2, 4)), poses,
        np.array([True, False]), np.arange(2)), ValueError, "non-finite")
    return checks


CASES: dict[str, Callable[[int, str], Checks]] = {
    "autocast_fp16_bf16": case_autocast,
    "huge_tiny_densities": case_densities,
    "near_far_touching": case_near_far,
    "axis_parallel_rays": case_axis_parallel,
    "far_outside_bounds": case_far_outside,
    "degenerate_rotation_6d": case_rotation_6d,
    "all_background_frames": case_all_background,
    "more_segments_than_slots": case_more_segments_than_slots,
    "equal_costs": case_equal_costs,
    "nonfinite_depth_confidence": case_nonfinite_inputs,
}
