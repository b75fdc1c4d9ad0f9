"""A campaign: many rows (a season) through the DAG, every row's NeRF windows on ONE Dask cluster.

Each row runs in its own thread with its own Runner, so the manifest skips what is up to date exactly
as `pag all` does. Stages other than nerf_fit run in this process and take turns (one lock: they use
this process's cores, and matplotlib is not thread-safe); nerf_fit only submits its windows to the
shared cluster (pipeline/parallel.shared_cluster) and waits, so while one row's windows are fitted the
next row is ingested, and the windows of all rows queue on the same workers: adding workers to the
cluster shortens the campaign. A row that fails is reported with its message; the others finish.
Afterwards the rows' tables are gathered into one dataset and a report (pipeline/campaign_dataset.py).
"""
from __future__ import annotations

import json
import os
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pipeline import campaign_dataset, dag, parallel
from pipeline import config as cfgmod
from pipeline.runner import PipelineError, Runner, StageResult

ROWS_SECTION = "rows"
"""Key of a campaign config file that holds per-row settings: rows: {SEQ: {section: {key: value}}}."""


@dataclass
class RowOutcome:
    seq: str
    status: str = "ok"
    """'ok' or 'failed'."""
    error: str = ""
    ran: list[str] = field(default_factory=list)
    skipped: list[str] = field(default_factory=list)
    seconds: float = 0.0


class _RowRunner(Runner):
    """A Runner whose in-process stages take the campaign's lock; nerf_fit (which waits on the cluster) does not."""

    def __init__(self, *args: Any, local_lock: threading.Lock, **kwargs: Any):
        super().__init__(*args, **kwargs)
        self.local_lock = local_lock
        self.current_stage = ""
        """the stage running (or last run): names the stage a failure came from."""

    def run_stage(self, s: dag.Stage, *args: Any, **kwargs: Any) -> StageResult:
        self.current_stage = s.name
        if s.name == "nerf_fit":
            return super().run_stage(s, *args, **kwargs)
        with self.local_lock:
            return super().run_stage(s, *args, **kwargs)


def as_overrides(mapping: dict[str, Any], prefix: str = "") -> list[str]:
    """{'synth': {'seed': 2}} -> ['synth.seed=2'] (values as JSON, which --set reads as YAML)."""
    out = []
    for key, value in mapping.items():
        name = f"{prefix}.{key}" if prefix else str(key)
        if isinstance(value, dict):
            out += as_overrides(value, name)
        else:
            out.append(f"{name}={json.dumps(value)}")
    return out


def is_synthetic_name(seq: str, data_root: Path) -> bool:
    """A row `pag synth` may (re)write: its name starts with 'synth' or its raw folder was written by it."""
    return seq.startswith("synth") or (Path(data_root) / "raw" / seq / "gt" / "synth_config.yaml").is_file()


def row_overrides(seqs: list[str], config_file: Path | None, overrides: list[str],
                  data_root: Path = Path("data")) -> dict[str, list[str]]:
    """Each row's settings as --set items: the config file's sections, then its rows.<SEQ> section, then the
    command line's --set (which wins). Settings of the synth section given for all rows reach only synthetic
    rows (is_synthetic_name): for a recorded row they would make the runner regenerate its raw folder."""
    raw = cfgmod.load_file(config_file)
    rows = raw.pop(ROWS_SECTION, None) or {}
    if not isinstance(rows, dict):
        raise cfgmod.ConfigError(f"config file {config_file}: '{ROWS_SECTION}' must map sequence names to sections, "
                                 f"got {rows!r}")
    unused = sorted(set(rows) - set(seqs))
    if unused:  # a season's file may list more rows than one campaign runs; a misspelt name shows here
        print(f"[pag campaign] {config_file}: settings of {ROWS_SECTION} {unused} unused (not in --seqs)", file=sys.stderr)
    base = as_overrides(raw)
    out = {}
    for seq in seqs:
        per_row = rows.get(seq) or {}
        if not isinstance(per_row, dict):
            raise cfgmod.ConfigError(f"config file {config_file}: {ROWS_SECTION}.{seq} must be a mapping of "
                                     f"sections, got {per_row!r}")
        common = (base, list(overrides))
        if not is_synthetic_name(seq, data_root):
            common = tuple([o for o in items if not o.strip().startswith("synth.")] for items in common)
        out[seq] = common[0] + as_overrides(per_row) + common[1]
    return out


def check_seqs(seqs: list[str]) -> None:
    if not seqs:
        raise PipelineError("pag campaign: give at least one sequence (--seqs SEQ [SEQ ...])")
    dup = sorted({s for s in seqs if seqs.count(s) > 1})
    if dup:
        raise PipelineError(f"pag campaign: sequences {dup} are given more than once")
    bad = [s for s in seqs if not s or "/" in s or s.startswith((".", "_"))]
    if bad:
        raise PipelineError(f"pag campaign: {bad} are not sequence folder names (names starting with '_' are "
                            f"reserved for data/processed/_campaign)")


def cluster_size(runners: list[Runner]) -> tuple[int, int]:
    """(workers, torch threads per worker) of the local cluster: as nerf_fit sizes its own (nerf_fit.workers,
    0 = one per core; nerf_fit.threads_per_worker, 0 = cores / workers), the largest over the rows."""
    cores = os.cpu_count() or 1
    workers = max(r.config["nerf_fit"].workers or cores for r in runners)
    threads = max(r.config["nerf_fit"].threads_per_worker for r in runners) or max(1, cores // workers)
    return workers, threads


def run_rows(seqs: list[str], data_root: Path = Path("data"), config_file: Path | None = None,
             overrides: list[str] | tuple[str, ...] = (), scheduler: str | None = None, force: bool = False,
             show_progress: bool | None = None) -> list[RowOutcome]:
    """Run every stage of every row (rows concurrently, windows on one cluster); one outcome per row, in order."""
    check_seqs(seqs)
    per_row = row_overrides(seqs, config_file, list(overrides), data_root)
    lock = threading.Lock()
    outcomes = {seq: RowOutcome(seq) for seq in seqs}
    runners: dict[str, _RowRunner] = {}
    for seq in seqs:
        try:
            runners[seq] = _RowRunner(seq, data_root=data_root, overrides=per_row[seq], local_lock=lock,
                                      show_progress=False if len(seqs) > 1 else show_progress)
        except Exception as err:  # a bad setting fails its row, not the campaign
            outcomes[seq].status, outcomes[seq].error = "failed", f"{type(err).__name__}: {err}"
    if not runners:
        return list(outcomes.values())
    workers, threads = cluster_size(list(runners.values()))
    scheduler = scheduler or next((r.config["run"].scheduler for r in runners.values() if r.config["run"].scheduler),
                                  None)
    if scheduler:  # torch threads per task: nerf_fit.threads_per_worker, else each worker's cores / task slots
        threads = max(r.config["nerf_fit"].threads_per_worker for r in runners.values())

    def one(seq: str) -> None:
        out, t0 = outcomes[seq], time.perf_counter()
        print(f"[pag campaign] {seq}: started", file=sys.stderr)
        try:
            for r in runners[seq].run(force=force):
                (out.ran if r.status == "ran" else out.skipped).append(r.stage)
        except Exception as err:
            stage = runners[seq].current_stage
            out.status, out.error = "failed", (f"stage {stage}: " if stage else "") + f"{type(err).__name__}: {err}"
        out.seconds = time.perf_counter() - t0
        print(f"[pag campaign] {seq}: {out.status} in {out.seconds:.1f} s ({len(out.ran)} stages ran, "
              f"{len(out.skipped)} up to date)" + (f": {out.error}" if out.error else ""), file=sys.stderr)

    with parallel.shared_cluster(scheduler, workers, threads), ThreadPoolExecutor(max_workers=len(runners)) as pool:
        list(pool.map(one, list(runners)))
    return [outcomes[s] for s in seqs]


def run_campaign(seqs: list[str], data_root: Path = Path("data"), config_file: Path | None = None,
                 overrides: list[str] | tuple[str, ...] = (), scheduler: str | None = None, force: bool = False,
                 show_progress: bool | None = None, track: bool = False) -> list[RowOutcome]:
    """run_rows, then the campaign dataset and report under data/processed/_campaign/ (one atomic swap). With
    `track`, the finished rows are first tracked as dates of one row (pipeline.season.track, into
    data/processed/_season/) and the report gains a season section (none, with a warning, when fewer than two
    rows finished)."""
    if track and len(set(seqs)) < 2:
        raise ValueError(f"pag campaign --track: a season needs at least two dates of the row, got {seqs}")
    outcomes = run_rows(seqs, data_root, config_file, overrides, scheduler, force, show_progress)
    section = ""
    ok = [o.seq for o in outcomes if o.status == "ok"]
    if track and len(ok) < 2:
        print(f"[pag campaign] --track: only {ok} finished; no season tracked", file=sys.stderr)
    elif track:
        from pipeline import season, season_report

        tracked, scores, _ = season.track(ok, Path(data_root))
        section = season_report.section(tracked, scores, level=3)
    campaign_dataset.write(Path(data_root), outcomes, section)
    return outcomes
