"""Encoding throughput: permutohedral vs cubic hash grid, pure-torch reference vs fused kernel.

Forward + backward, side by side in one process on the same points, in two gradient
configurations ('table': table gradients only; 'table+x': table and position gradients, as when
camera poses are optimised) and two point sets ('uniform' in [-1, 1]^3; 'rays': 64 samples along
each of N/64 random rays, as a renderer produces them). Every round runs every variant once, in
turn, so machine noise hits all alike; medians over rounds are reported.

Also measured in the same run, the machine's own limit: a C++ loop doing, per point and level,
4 random reads ('mem_4r': what a forward must read) or 4 random reads plus 4 random
read-modify-writes ('mem_4r4u': what forward + table gradient must touch) in a table of the same
size, scheduled like the kernels. It moves no features and computes no lattice, so it is a floor.

On a GPU (`--device cuda`) the same variants run there (each timed to the end of its kernels), and the
limit is torch's own gather ('mem_4r': index_select of 4 random table rows per point and level) and gather
plus scatter-add ('mem_4r4u') on the same table: a floor of what the device's random access allows through
torch, with no lattice and no fused kernel of its own.

Output `encoding.parquet`, one row per (points, grads, variant):
    points, grads, variant, device, n_points, levels, features, log2_capacity, threads, repeats,
    median_s, mpts_per_s (million points per second, all levels), ns_per_point_level,
    speedup_vs_torch  (fused rows: reference median / fused median, same lattice),
    speedup_vs_cubic  (permuto_fused rows: cubic_fused median / permuto_fused median),
    fraction_of_limit (fused rows: limit median / kernel median, limit = mem_4r4u)
and `encoding.png` (throughput per variant, log scale).

    pag bench encoding [--points 65536] [--levels 16] [--features 2] [--log2-capacity 18]
                       [--repeats 7] [--threads N] [--device cpu|cuda] [--out data/bench]
"""
from __future__ import annotations

import argparse
import statistics
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from bench._common import interleaved_medians, write_parquet
from nerf._ext import load_permuto_ext
from nerf.encoding import CubicHashEncoding, PermutoEncoding

ENCODINGS = {"permuto": PermutoEncoding, "cubic": CubicHashEncoding}
SAMPLES_PER_RAY = 64


def sample_points(n: int, kind: str, seed: int = 0) -> torch.Tensor:
    """[n, 3] points: 'uniform' in [-1, 1]^3, or 'rays': 64 evenly spaced samples along each of
    n / 64 random rays crossing the cube (neighbouring samples share lattice cells, as in rendering)."""
    g = torch.Generator().manual_seed(seed)
    if kind == "uniform":
        return torch.rand(n, 3, generator=g) * 2 - 1
    if kind != "rays":
        raise ValueError(f"unknown point set {kind!r}; point sets: ['uniform', 'rays']")
    n_rays = -(-n // SAMPLES_PER_RAY)
    o = torch.rand(n_rays, 3, generator=g) * 2 - 1
    d = torch.nn.functional.normalize(torch.randn(n_rays, 3, generator=g), dim=1)
    t = torch.linspace(0.0, 1.0, SAMPLES_PER_RAY)
    pts = o[:, None] + d[:, None] * t[None, :, None]
    return pts.reshape(-1, 3)[:n].clamp(-1, 1).contiguous()


def _train_step(enc: torch.nn.Module, x: torch.Tensor, grad_x: bool) -> Callable[[], None]:
    """Forward, then backward of a fixed dense upstream gradient (what the decoder hands the encoding in
    training; `.sum().backward()` would hand it a stride-0 tensor that the kernel first has to copy out)."""
    grad_out = torch.randn(x.shape[0], enc.out_dim, generator=torch.Generator().manual_seed(1)).to(x.device)

    def step() -> None:
        xx = x.detach().requires_grad_(grad_x)
        enc(xx).backward(grad_out)
        enc.table.grad = None
    return _synced(step, x.device)


def _synced(fn: Callable[[], None], device: torch.device) -> Callable[[], None]:
    """fn, returning only once the device has finished its work (CUDA runs kernels asynchronously)."""
    if device.type != "cuda":
        return fn

    def run() -> None:
        fn()
        torch.cuda.synchronize(device)
    return run


def _gather_limits(table: torch.Tensor, offsets: torch.Tensor, n_points: int, ext) -> dict[str, Callable[[], None]]:
    """The random-access floor on the table's device (rows [R, F], level offsets [L + 1]): 4 random rows read per
    point and level ('mem_4r'), or read and updated ('mem_4r4u'). The CPU's is the fused module's own loop; a
    GPU's is torch's gather and scatter-add."""
    if table.device.type == "cpu":
        return {"mem_4r": lambda: ext.random_access(table, offsets, n_points, 4, 0),
                "mem_4r4u": lambda: ext.random_access(table, offsets, n_points, 4, 4)}
    rows = table
    idx = torch.randint(0, rows.shape[0], (4 * (len(offsets) - 1) * n_points,), device=table.device,
                        generator=torch.Generator(table.device).manual_seed(2))
    acc = torch.zeros_like(rows)

    def read_update() -> None:
        acc.index_add_(0, idx, rows.index_select(0, idx))
    return {"mem_4r": _synced(lambda: rows.index_select(0, idx), table.device),
            "mem_4r4u": _synced(read_update, table.device)}


def run(n_points: int = 2 ** 16, n_levels: int = 16, n_features: int = 2, log2_capacity: int = 18, repeats: int = 7,
        threads: int | None = None, out_dir: Path = Path("data/bench"), device: str = "cpu") -> pd.DataFrame:
    """Measure on `device` ('cpu', 'cuda', 'cuda:N'), write `encoding.parquet` and `encoding.png` under out_dir,
    return the table."""
    if n_points < 1 or repeats < 1:
        raise ValueError(f"need n_points >= 1 and repeats >= 1, got {n_points}, {repeats}")
    dev = torch.device(device)
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise RuntimeError(f"--device {device}: torch {torch.__version__} sees no CUDA device")
    ext = load_permuto_ext(dev.type)
    if ext is None:
        raise RuntimeError(f"the fused {dev.type} kernel could not be built (see the warning above), so there is "
                           "nothing to compare the reference with")
    old_threads = torch.get_num_threads()
    if threads is not None:
        torch.set_num_threads(threads)
    try:
        kw = dict(n_levels=n_levels, n_features=n_features, log2_capacity=log2_capacity, coarsest_scale=1.0,
                  finest_scale=1 / 2048, init_std=1e-2)
        encs = {f"{name}_{backend}": cls(**kw, backend=backend).to(dev)
                for name, cls in ENCODINGS.items() for backend in ("torch", "fused")}
        enc = encs["permuto_fused"]
        limits = _gather_limits(enc.table.detach(), enc.offsets.cpu(), n_points, ext)
        rows = []
        for kind in ("uniform", "rays"):
            x = sample_points(n_points, kind).to(dev)
            for grads in ("table", "table+x"):
                variants = {k: _train_step(e, x, grads == "table+x") for k, e in encs.items()} | limits
                for name, ts in interleaved_medians(variants, repeats).items():
                    med = statistics.median(ts)
                    rows.append({"points": kind, "grads": grads, "variant": name, "device": str(dev),
                                 "n_points": n_points, "levels": n_levels, "features": n_features,
                                 "log2_capacity": log2_capacity, "threads": torch.get_num_threads(),
                                 "repeats": len(ts), "median_s": med, "mpts_per_s": n_points / med / 1e6,
                                 "ns_per_point_level": med / (n_points * n_levels) * 1e9})
    finally:
        torch.set_num_threads(old_threads)
    df = _with_ratios(pd.DataFrame(rows))
    out_dir.mkdir(parents=True, exist_ok=True)
    write_parquet(df, out_dir / "encoding.parquet")
    plot(df, out_dir / "encoding.png")
    return df


def _with_ratios(df: pd.DataFrame) -> pd.DataFrame:
    df = df.copy()
    for col in ("speedup_vs_torch", "speedup_vs_cubic", "fraction_of_limit"):
        df[col] = np.nan
    for _, g in df.groupby(["points", "grads"]):
        med = g.set_index("variant")["median_s"]
        for lat in ENCODINGS:
            i = g.index[g.variant == f"{lat}_fused"][0]
            df.loc[i, "speedup_vs_torch"] = med[f"{lat}_torch"] / med[f"{lat}_fused"]
            df.loc[i, "fraction_of_limit"] = med["mem_4r4u"] / med[f"{lat}_fused"]
        df.loc[g.index[g.variant == "permuto_fused"][0], "speedup_vs_cubic"] = med["cubic_fused"] / med["permuto_fused"]
    return df


def plot(df: pd.DataFrame, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    configs = list(df.groupby(["points", "grads"], sort=False).groups)
    variants = list(dict.fromkeys(df.variant))
    fig, ax = plt.subplots(figsize=(9, 4))
    width = 0.8 / len(configs)
    for c, (kind, grads) in enumerate(configs):
        g = df[(df.points == kind) & (df.grads == grads)].set_index("variant")
        vals = [g.loc[v, "mpts_per_s"] for v in variants]
        xs = np.arange(len(variants)) + (c - (len(configs) - 1) / 2) * width
        ax.bar(xs, vals, width, label=f"{kind}, grads: {grads}")
    ax.set_xticks(np.arange(len(variants)), variants, fontsize=8)
    ax.set_yscale("log")
    ax.set_ylabel("M points / s (forward + backward)")
    r = df.iloc[0]
    ax.set_title(f"hash-grid encodings: {r.n_points} points, {r.levels} levels x {r.features} features, "
                 f"T = 2^{r.log2_capacity}, {r.threads} threads (mem_* = random-access floor)", fontsize=9)
    ax.legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)


def summary(df: pd.DataFrame) -> str:
    cols = ["points", "grads", "variant", "median_s", "mpts_per_s", "ns_per_point_level", "speedup_vs_torch",
            "speedup_vs_cubic", "fraction_of_limit"]
    return df[cols].to_string(index=False, float_format=lambda v: f"{v:.3g}", na_rep="")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="pag bench encoding", description=__doc__.split("\n")[0])
    p.add_argument("--points", type=int, default=2 ** 16, help="points per step")
    p.add_argument("--levels", type=int, default=16)
    p.add_argument("--features", type=int, default=2, help="features per level")
    p.add_argument("--log2-capacity", type=int, default=18, help="log2 of the table size per level")
    p.add_argument("--repeats", type=int, default=7, help="interleaved rounds (medians are reported)")
    p.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's current setting)")
    p.add_argument("--device", default="cpu", help="torch device: cpu, cuda or cuda:N")
    p.add_argument("--out", type=Path, default=Path("data/bench"), help="output folder")
    a = p.parse_args(argv)
    df = run(a.points, a.levels, a.features, a.log2_capacity, a.repeats, a.threads, a.out, a.device)
    print(summary(df))
    print("targets: speedup_vs_torch >= 10 (fused vs reference), speedup_vs_cubic >= 1.25 (permuto vs cubic, fused)")
    print(f"written: {a.out / 'encoding.parquet'}, {a.out / 'encoding.png'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
