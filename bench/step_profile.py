"""Where a training step's time goes: the colour fit of one window under torch's profiler, op by op.

Fits window `--window` of `--seq` (the nerf_fit stage's model settings, its depth-corrected initial poses, the
poses moving from the first step) for 1 + `--steps` colour steps under the profiler (after an unprofiled fit of 2
steps that loads the fused kernel and warms the allocator); only the ops that start after the first step ends
and before the last one ends are counted, so the window's set-up is left out. Each op's self CPU time is put in
one group (encoding, decoders, marching, compositing and losses, optimiser, pose and rays, occupancy updates,
pixel sampling, other) and the groups are reported as shares of the steps' wall time; what no op accounts for
(Python between ops, the marching kernel, which is not a torch op) is its own group. The encoding is also held
against the machine's own limit, as `pag bench encoding` does: the C++ loop that makes the random table reads
and read-modify-writes (4 + 4 per point and level) the forward and backward must make, timed on the same number
of points per step (the samples the steps encoded).

Output `step_profile.parquet`: one row per group (group, seconds, share, ms_per_step), then one per op of the
largest 15 (group 'op:<group>', op name), with the run's size columns (seq, window, width, height, steps,
rays_per_step, samples_per_step, threads, wall_ms_per_step) and, on the encoding row, `limit_ms_per_step` and
`fraction_of_limit` (limit / measured: 1 = at the machine's limit).

With `--scaling 1,2`: instead of the profile, the steps' wall time at each thread count, in interleaved rounds
(median of `--rounds`), into `step_threads.parquet` (threads, median_ms_per_step, speedup over the first count):
what the last window of a row gains when it takes the cores of finished workers (nerf_fit.threads_per_worker=0).

    pag bench step_profile [--seq synth_bup20] [--window 0] [--steps 60] [--threads 1] [--data-root data]
                           [--out data/bench] [--scaling 1,2 --rounds 3]
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time
from dataclasses import replace
from pathlib import Path

import pandas as pd
import torch

from bench._common import read, window_rows, write_parquet
from nerf.depth_poses import depth_initial_poses
from nerf.trainer import fit_window
from rowmap.window_data import initial_poses, load_window

GROUPS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("encoding", ("FusedEncode", "permuto", "encode")),
    ("marching", ("march",)),
    ("optimiser", ("adam", "Optimizer", "lr_scheduler")),
    ("decoders", ("ChunkedMLP", "addmm", "aten::mm", "linear", "relu", "threshold_backward", "aten::t", "sigmoid",
                  "softplus", "exp_backward", "aten::cat", "matmul")),
    ("compositing and losses", ("cumsum", "index_add", "scatter", "segment", "gather", "aten::exp", "aten::mul",
                                "aten::sub", "aten::add", "aten::div", "aten::sum", "aten::mean", "aten::abs",
                                "pow", "aten::neg", "aten::clamp", "aten::where", "aten::index", "masked")),
    ("pose and rays", ("pose", "rays", "bmm", "cross", "normalize", "linalg")),
    ("occupancy", ("max_pool3d", "occupan")),
    ("pixel sampling", ("normal_", "multinomial", "searchsorted", "uniform_", "random_", "randint")),
)
"""Group -> substrings of profiler op names (first match wins, case-insensitive); the rest is 'other'."""


UNTRACED = "untraced (Python, marching kernel)"
"""The group of the steps' wall time that no profiled op accounts for."""
STEP_MARK = "step_profile::mark"
"""The profiler range dropped after the first and after the last profiled step."""


def group_of(op: str) -> str:
    low = op.lower()
    for name, keys in GROUPS:
        if any(k.lower() in low for k in keys):
            return name
    return "other"


def steps_self_seconds(events) -> pd.Series:
    """Self CPU seconds per op name of the events that start between the first and the last STEP_MARK."""
    starts = sorted(e.time_range.start for e in events if e.name == STEP_MARK)
    lo, hi = starts[0], starts[-1]
    secs: dict[str, float] = {}
    for e in events:
        if e.name != STEP_MARK and lo < e.time_range.start < hi:
            secs[e.name] = secs.get(e.name, 0.0) + e.self_cpu_time_total / 1e6
    return pd.Series(secs, dtype=float)


def encoding_limit_s(model, n_points: int, repeats: int = 5) -> float:
    """Median seconds of the machine's floor for encoding `n_points` points forward + backward at the model's
    table size: 4 random reads plus 4 read-modify-writes per point and level (bench/encoding.py's mem_4r4u)."""
    from nerf._ext import load_permuto_ext

    ext = load_permuto_ext("cpu")
    grid = getattr(model.field, "grid", None)
    if ext is None or grid is None:
        return float("nan")
    table, offsets = grid.table.detach().float().contiguous(), grid.offsets.cpu()
    ext.random_access(table, offsets, n_points, 4, 4)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        ext.random_access(table, offsets, n_points, 4, 4)
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def fitted_window(data_root: Path, seq: str, window: int):
    """The window as nerf_fit fits it (depth-corrected initial poses) and the stage's model settings, with the
    poses moving from the first step and no final registration (only steps are timed)."""
    from pipeline import dag

    stage = dag.load_stage("nerf_fit").module     # through the DAG, as stage_defaults does: no stage import here
    stage_cfg = stage.Config()
    cfg = stage.model_config(stage_cfg)
    w, _ = window_rows(data_root, seq, window)
    w = initial_poses(w, window, None, "odometry")
    data = load_window(w, data_root)
    data.poses_c2w, _ = depth_initial_poses(stage_cfg.depth_poses, data.depths, data.intrinsics,
                                            data.poses_c2w)
    return data, replace(cfg, pose_warmup_steps=0, val_register_final_steps=0)


def step_seconds(data, cfg, steps: int) -> float:
    """Wall seconds per colour step of a fit, the set-up left out (timed from the first step's progress call)."""
    marks: list[float] = []
    fit_window(data, replace(cfg, steps=steps + 1), render_val=False,
               progress=lambda done, total, info: marks.append(time.perf_counter()) if done in (1, steps + 1) else None)
    return (marks[-1] - marks[0]) / steps


def thread_scaling(data_root: Path, seq: str, window: int, steps: int, counts: list[int], rounds: int
                   ) -> pd.DataFrame:
    """Median seconds per step at each torch thread count in `counts`, the counts interleaved in every round."""
    data, cfg = fitted_window(data_root, seq, window)
    fit_window(data, replace(cfg, steps=2), render_val=False)  # kernel, allocator
    steps = max(50, steps - steps % 50)  # progress comes every 50 steps
    times: dict[int, list[float]] = {n: [] for n in counts}
    for _ in range(rounds):
        for n in counts:
            torch.set_num_threads(n)
            times[n].append(step_seconds(data, cfg, steps))
    med = {n: statistics.median(t) for n, t in times.items()}
    return pd.DataFrame([{"seq": seq, "window": window, "width": data.images.shape[2], "steps": steps,
                          "rounds": rounds, "threads": n, "median_ms_per_step": med[n] * 1e3,
                          "speedup": med[counts[0]] / med[n]} for n in counts])


def profile(data_root: Path, seq: str, window: int, steps: int, threads: int) -> pd.DataFrame:
    torch.set_num_threads(threads)
    data, cfg = fitted_window(data_root, seq, window)
    fit_window(data, replace(cfg, steps=2), render_val=False)  # kernel, allocator
    # one profiled fit of steps + 1 steps; progress comes after the first and the last step (and every 50th), so
    # a marker dropped at those two calls brackets the last `steps` steps: the set-up and the first step are out
    marks: list[float] = []

    def mark(done: int, total: int, info: dict) -> None:
        if done in (1, total):
            marks.append(time.perf_counter())
            with torch.profiler.record_function(STEP_MARK):
                pass

    with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU]) as prof:
        res = fit_window(data, replace(cfg, steps=steps + 1), render_val=False, progress=mark)
    per_step = (marks[-1] - marks[0]) / steps
    secs = steps_self_seconds(prof.events())
    ops = pd.DataFrame({"op": secs.index, "seconds": secs.to_numpy()})
    # what the profiler does not see: Python between ops and the marching kernel (called outside torch's ops)
    untraced = max(0.0, per_step * steps - float(secs.sum()))
    ops = pd.concat([ops, pd.DataFrame([{"op": UNTRACED, "seconds": untraced}])], ignore_index=True)
    ops["group"] = ops.op.map(lambda op: UNTRACED if op == UNTRACED else group_of(op))
    total = ops.seconds.sum()
    samples = float(res.history[-1]["samples_per_ray"]) * cfg.rays_for(data.images.shape[1] * data.images.shape[2])
    groups = ops.groupby("group", as_index=False).seconds.sum().sort_values("seconds", ascending=False)
    groups["share"] = groups.seconds / total
    groups["ms_per_step"] = groups.seconds / steps * 1e3
    limit = encoding_limit_s(res.model, int(samples)) * 1e3 if samples > 0 else float("nan")
    groups["limit_ms_per_step"] = groups.group.map({"encoding": limit})
    groups["fraction_of_limit"] = groups.limit_ms_per_step / groups.ms_per_step
    top = ops.sort_values("seconds", ascending=False).head(15).assign(
        share=lambda d: d.seconds / total, ms_per_step=lambda d: d.seconds / steps * 1e3,
        group=lambda d: "op:" + d.group)
    out = pd.concat([groups, top], ignore_index=True)
    return out.assign(seq=seq, window=window, width=data.images.shape[2], height=data.images.shape[1], steps=steps,
                      rays_per_step=cfg.rays_for(data.images.shape[1] * data.images.shape[2]),
                      samples_per_step=samples, threads=threads, wall_ms_per_step=per_step * 1e3)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="pag bench step_profile", description=__doc__.split("\n")[0])
    p.add_argument("--seq", default="synth_bup20", help="a sequence with its windows stage done")
    p.add_argument("--window", type=int, default=0)
    p.add_argument("--steps", type=int, default=60, help="profiled colour steps (>= 1)")
    p.add_argument("--threads", type=int, default=1, help="torch threads (a nerf_fit worker on 2 cores has 1)")
    p.add_argument("--data-root", type=Path, default=Path("data"))
    p.add_argument("--out", type=Path, default=Path("data/bench"))
    p.add_argument("--scaling", default="", help="comma-separated thread counts: time the steps at each instead")
    p.add_argument("--rounds", type=int, default=3, help="rounds of --scaling (>= 1)")
    a = p.parse_args(argv)
    if a.steps < 1 or a.threads < 1 or a.rounds < 1:
        p.error("--steps, --threads and --rounds must be >= 1")
    counts = [int(c) for c in a.scaling.split(",") if c.strip()]
    if any(c < 1 for c in counts):
        p.error(f"--scaling takes thread counts >= 1, got {a.scaling!r}")
    read(a.data_root, a.seq, "windows")  # a clear error naming the stage to run first
    if counts:
        df = thread_scaling(a.data_root, a.seq, a.window, a.steps, counts, a.rounds)
        write_parquet(df, a.out / "step_threads.parquet")
        print(df.to_string(index=False, float_format=lambda v: f"{v:.3g}"))
        print(f"wrote {a.out / 'step_threads.parquet'}")
        return 0
    df = profile(a.data_root, a.seq, a.window, a.steps, a.threads)
    write_parquet(df, a.out / "step_profile.parquet")
    show = ["group", "op", "seconds", "share", "ms_per_step", "limit_ms_per_step", "fraction_of_limit"]
    print(df[[c for c in show if c in df]].to_string(index=False, float_format=lambda v: f"{v:.3g}"))
    print(f"wrote {a.out / 'step_profile.parquet'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
