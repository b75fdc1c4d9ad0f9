"""Encoding throughput: permutohedral (torch reference, fused) vs cubic hash grid (reference, fused),
forward + backward (table and position gradients), side by side in one process on the same points,
plus a random-read microbenchmark of the machine's limit.

    pag bench encoding [--points 65536] [--levels 16] [--features 2] [--log2-capacity 18] [--repeats 7]
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from bench._common import bar_plot, interleaved_medians, median, write_parquet
from nerf._ext import load_permuto_ext
from nerf.encoding import CubicHashEncoding, PermutoEncoding


def sample_points(n: int, kind: str, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    if kind == "uniform":
        return torch.rand(n, 3, generator=g) * 2 - 1
    # along rays: 64 samples on each of n/64 rays through the unit cube, as a renderer produces them
    n_rays = max(1, n // 64)
    o = torch.rand(n_rays, 3, generator=g) * 2 - 1
    d = torch.nn.functional.normalize(torch.randn(n_rays, 3, generator=g), dim=1)
    t = torch.linspace(0, 0.5, 64)
    return (o[:, None] + d[:, None] * t[None, :, None]).reshape(-1, 3)[:n].contiguous()


def step(enc: torch.nn.Module, x: torch.Tensor, grad_x: bool) -> None:
    xx = x.detach().requires_grad_(grad_x)
    enc(xx).sum().backward()
    enc.table.grad = None


def run(n_points: int = 2 ** 16, n_levels: int = 16, n_features: int = 2, log2_capacity: int = 18, repeats: int = 7,
        ref_repeats: int = 3, out_dir: Path = Path("data/bench")) -> pd.DataFrame:
    ext = load_permuto_ext("cpu")
    if ext is None:
        raise RuntimeError("the fused kernel could not be built, so there is nothing to compare (see the warning)")
    kw = dict(n_levels=n_levels, n_features=n_features, log2_capacity=log2_capacity, finest_scale=1 / 2048)
    encs = {"permuto_fused": PermutoEncoding(**kw, backend="fused"), "cubic_fused": CubicHashEncoding(**kw, backend="fused"),
            "permuto_torch": PermutoEncoding(**kw, backend="torch"), "cubic_torch": CubicHashEncoding(**kw, backend="torch")}
    rows = []
    for kind in ("uniform", "rays"):
        x = sample_points(n_points, kind)
        for grad_x in (False, True):
            fast = {k: (lambda e=e: step(e, x, grad_x)) for k, e in encs.items() if k.endswith("fused")}
            slow = {k: (lambda e=e: step(e, x, grad_x)) for k, e in encs.items() if k.endswith("torch")}
            times = interleaved_medians(fast, repeats) | interleaved_medians(slow, ref_repeats, warmup=0)
            limit = interleaved_medians({"random_reads_4": lambda: ext.random_reads(n_points, n_levels, 2 ** log2_capacity,
                                                                                    n_features, 4)}, repeats)
            times |= limit
            for name, ts in times.items():
                rows.append({"points": kind, "grad_x": grad_x, "variant": name, "n_points": n_points,
                             "levels": n_levels, "log2_capacity": log2_capacity, "threads": torch.get_num_threads(),
                             "median_s": median(ts), "mpts_per_s": n_points / median(ts) / 1e6, "repeats": len(ts)})
    df = pd.DataFrame(rows)
    out_dir.mkdir(parents=True, exist_ok=True)
    write_parquet(df, out_dir / "encoding.parquet")
    main_rows = df[(df.points == "rays") & df.grad_x].set_index("variant")
    bar_plot(list(main_rows.index), list(main_rows.mpts_per_s), "M points/s (fwd+bwd, table+x grads)",
             f"encoding, {n_points} pts on rays, {n_levels} levels, T=2^{log2_capacity}, "
             f"{torch.get_num_threads()} threads", out_dir / "encoding.png")
    return df


def ratios(df: pd.DataFrame) -> pd.DataFrame:
    out = []
    for (kind, gx), g in df.groupby(["points", "grad_x"]):
        m = g.set_index("variant")["median_s"]
        out.append({"points": kind, "grad_x": gx, "fused_vs_torch": m["permuto_torch"] / m["permuto_fused"],
                    "permuto_vs_cubic_fused": m["cubic_fused"] / m["permuto_fused"],
                    "fused_vs_4_random_reads": m["random_reads_4"] / m["permuto_fused"]})
    return pd.DataFrame(out)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="pag bench encoding", description=__doc__.split("\n")[0])
    p.add_argument("--points", type=int, default=2 ** 16)
    p.add_argument("--levels", type=int, default=16)
    p.add_argument("--features", type=int, default=2)
    p.add_argument("--log2-capacity", type=int, default=18)
    p.add_argument("--repeats", type=int, default=7)
    p.add_argument("--out", type=Path, default=Path("data/bench"))
    a = p.parse_args(argv)
    df = run(a.points, a.levels, a.features, a.log2_capacity, a.repeats, out_dir=a.out)
    with pd.option_context("display.width", 160, "display.max_columns", 20):
        print(df[["points", "grad_x", "variant", "median_s", "mpts_per_s"]].to_string(index=False))
        print("\nratios of medians (targets: fused_vs_torch >= 10, permuto_vs_cubic_fused >= 1.25):")
        print(ratios(df).to_string(index=False, float_format=lambda v: f"{v:.2f}"))
    print(f"\nwritten: {a.out / 'encoding.parquet'}, {a.out / 'encoding.png'}")
    return 0
