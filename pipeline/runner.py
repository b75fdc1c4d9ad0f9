"""The runner: resolves config, loads each stage's inputs from the catalog, runs it, validates and
writes its outputs atomically, and skips stages whose code, config and inputs are unchanged
(a manifest of content hashes per stage under data/interim/<SEQ>/_manifest/).
"""
from __future__ import annotations

import contextlib
import hashlib
import importlib
import json
import logging
import shutil
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pandas as pd
import yaml

from nerf.memory import release_freed
from pipeline import config as cfgmod
from pipeline import codehash, dag, io, provenance
from pipeline.catalog import DATASETS, dataset
from pipeline.lock import RowLock
from pipeline.resources import PeakMemory
from pipeline.stage import StageContext

log = logging.getLogger("pag")
REPO_ROOT = Path(__file__).resolve().parents[1]


RUN_KEYS_WITHOUT_EFFECT = ("progress", "progress_interval_s")
"""Settings of section `run` that change what is shown, not what is computed (not part of a stage's key)."""


class PipelineError(RuntimeError):
    """A stage could not run or failed; the message says which and why."""


def torch_device(name: str) -> str:
    """The torch device that run.device names: 'auto' is 'cuda' (the GPUs) where torch sees one, else 'cpu'. A GPU
    that torch does not see is an error, not a silent run on the CPU."""
    import torch

    if name == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if name.startswith("cuda"):
        index = int(name.partition(":")[2] or 0)
        if index >= torch.cuda.device_count():
            raise PipelineError(f"run.device={name}, but torch {torch.__version__} sees {torch.cuda.device_count()} "
                                f"CUDA device(s) (its CUDA build: {torch.version.cuda}); use run.device=auto or "
                                "cpu, or install a CUDA build of torch (README, 'On a GPU machine')")
    return name


@dataclass
class StageResult:
    stage: str
    status: str  # "ran" | "skipped"
    seconds: float = 0.0
    summary: dict[str, Any] = field(default_factory=dict)
    peak_rss_mb: float = 0.0
    """largest resident memory of the pipeline process and its workers while the stage ran (MiB, sampled)."""


def code_hash(stage: dag.Stage) -> str:
    """Hash of the code the stage's result depends on: its module, every project module it imports
    (transitively, pipeline/ included; docstrings and comments do not count, see pipeline/codehash.py) and
    the schemas its output tables are validated with (schemas.get imports those by name)."""
    schema_modules = [f"schemas.{dataset(o).schema}" for o in stage.outputs if dataset(o).kind == "table"]
    files = {m: Path(importlib.import_module(m).__file__) for m in schema_modules}
    files[stage.module.__name__] = Path(stage.module.__file__)
    return codehash.code_hash([stage.module.__name__, *schema_modules], REPO_ROOT, files=files)


def valid_seq(seq: str) -> bool:
    """A sequence is a folder under data/raw/: one name, or names joined by '/' (a BUP20 release placed under
    data/raw/ gives `20200924/row3`). Names may hold spaces and non-ASCII letters; never absolute, no empty
    part, no part starting with '.' (so never '..'), no backslash or control character."""
    parts = seq.split("/")
    return bool(seq) and all(p and not p.startswith(".") and p == p.strip() and "\\" not in p
                             and all(c.isprintable() for c in p) for p in parts)


class Runner:
    def __init__(self, seq: str, data_root: Path = Path("data"), config_file: Path | None = None,
                 overrides: list[str] | tuple[str, ...] = (), show_progress: bool | None = None,
                 stages: list[dag.Stage] | None = None):
        if not valid_seq(seq):
            raise PipelineError(f"--seq must be a folder name under data/raw/, or such names joined by '/' for a nested "
                                f"folder such as 20200924/row3 (no empty part, no part starting with '.', no leading "
                                f"or trailing space); got {seq!r}")
        self.seq = seq
        self.data_root = Path(data_root)
        self.stages = dag.check(stages) if stages is not None else dag.build()
        raw_cfg = cfgmod.merge(cfgmod.load_file(config_file), cfgmod.parse_set(list(overrides)))
        sections: dict[str, type] = {"run": cfgmod.RunConfig}
        sections.update({s.name: s.config_class for s in self.stages})
        self.config = cfgmod.resolve(sections, raw_cfg)
        self.synthetic = (seq.startswith("synth") or "synth" in raw_cfg
                          or (self.raw_dir / "gt" / "synth_config.yaml").is_file())
        self.show_progress = self.config["run"].progress if show_progress is None else show_progress
        self.manifest_dir = self.data_root / "interim" / seq / "_manifest"
        self.resume_root = self.data_root / "interim" / seq / "_resume"
        self.hashes = io.HashCache(self.manifest_dir / "hashcache.json")
        self.lock = RowLock(self.data_root, seq)

    @property
    def raw_dir(self) -> Path:
        return dataset("raw").path(self.data_root, self.seq)

    def active(self) -> list[dag.Stage]:
        """Stages that run for this sequence (synth only for synthetic rows; disabled optional stages out)."""
        out = []
        for s in self.stages:
            if s.name == "synth" and not self.synthetic:
                continue
            if getattr(self.config[s.name], "enabled", True) is False:
                continue
            out.append(s)
        return out

    def write_resolved_config(self) -> None:
        text = yaml.safe_dump({k: cfgmod.to_dict(v) for k, v in self.config.items()}, sort_keys=False).encode()
        for area in ("interim", "processed"):
            io.atomic_write_bytes(self.data_root / area / self.seq / "config.resolved.yaml", text)

    # -- running -------------------------------------------------------------------------------
    def run(self, targets: list[str] | None = None, force: bool = False) -> list[StageResult]:
        """Run `targets` (stage names) or every active stage, in DAG order."""
        active = self.active()
        names = [s.name for s in active]
        if targets:
            unknown = [t for t in targets if t not in [s.name for s in self.stages]]
            if unknown:
                raise PipelineError(f"unknown stage(s) {unknown}; stages: {[s.name for s in self.stages]}")
            if "synth" in targets and not self.synthetic:
                raise PipelineError(
                    f"sequence {self.seq!r} is not synthetic (name does not start with 'synth' and no synth.* "
                    f"setting given); `pag synth` would overwrite data/raw/{self.seq}. Use --seq synth_<name>.")
            chosen = [s for s in self.stages if s.name in targets]
        else:
            chosen = active
        self.check_raw(chosen)
        with self.lock:  # one run per row; released by the kernel if this process is killed
            self.remove_leftovers()
            self.write_resolved_config()
            results = []
            for s in chosen:
                results.append(self.run_stage(s, force=force))
            self.hashes.save()
        return results

    def remove_leftovers(self) -> None:
        """Delete temp files, staging and swap folders a killed run of this row left behind (the row lock
        is held, so no other live process is writing them)."""
        n = io.remove_leftovers([self.data_root / "interim" / self.seq, self.data_root / "processed" / self.seq])
        n += io.remove_leftovers([self.raw_dir.parent], prefix=f".{self.seq}.", recursive=False)
        if n:
            print(f"[pag] removed {n} temp file(s)/folder(s) left by an interrupted run", file=sys.stderr)

    def check_raw(self, chosen: list[dag.Stage]) -> None:
        needs_raw = any("raw" in s.inputs for s in chosen)
        makes_raw = any(s.name == "synth" for s in chosen)
        if needs_raw and not makes_raw and not self.raw_dir.is_dir():
            root = self.data_root / "raw"
            # hidden folders are no sequences (valid_seq refuses them): a synth run's .<SEQ>.staging-<pid>
            have = sorted(p.name for p in root.iterdir() if p.is_dir() and not p.name.startswith(".")) \
                if root.is_dir() else []
            hint = ("run `pag synth` (or `pag all`) first to generate it" if self.synthetic else
                    "put a recorded row there: a BUP20-style folder (rgb/, depth/, odometry.csv, params.yaml, "
                    "pred_seg/, annotations.json) or a ROS 1/ROS 2 bag with pred_seg/ beside it (see data/README.md); "
                    "synthetic rows are made by names starting with 'synth'")
            raise PipelineError(f"sequence {self.seq!r} not found: {self.raw_dir} does not exist; {hint}. "
                                f"Sequences present: {have or 'none'}")

    def _input_path(self, name: str) -> Path:
        return dataset(name).path(self.data_root, self.seq)

    def stage_key(self, s: dag.Stage) -> tuple[str, dict[str, str]]:
        input_hashes = {}
        for name in s.inputs + s.optional_inputs:
            path = self._input_path(name)
            if name in s.inputs and not path.exists():
                producer = dag.producers(self.stages).get(name)
                how = f"run `pag {producer} --seq {self.seq}` first (or `pag all`)" if producer else "see data/README.md"
                raise PipelineError(f"stage {s.name!r} needs {name!r} ({path}), which does not exist; {how}")
            input_hashes[name] = self.hashes.tree_hash(path)
        run_cfg = {k: v for k, v in cfgmod.to_dict(self.config["run"]).items() if k not in RUN_KEYS_WITHOUT_EFFECT}
        payload = json.dumps({"code": code_hash(s), "config": cfgmod.to_dict(self.config[s.name]),
                              "run": run_cfg if s.name == "nerf_fit" else None,
                              "inputs": input_hashes, "seq": self.seq}, sort_keys=True, default=str)
        return hashlib.blake2b(payload.encode(), digest_size=16).hexdigest(), input_hashes

    def manifest_path(self, s: dag.Stage) -> Path:
        return self.manifest_dir / f"{s.name}.json"

    def is_fresh(self, s: dag.Stage, key: str) -> bool:
        path = self.manifest_path(s)
        if not path.is_file():
            return False
        try:
            rec = json.loads(path.read_text())
        except json.JSONDecodeError:
            return False
        if rec.get("key") != key:
            return False
        return all(self.hashes.tree_hash(self._input_path(o)) == h for o, h in rec.get("outputs", {}).items()) \
            and set(rec.get("outputs", {})) == set(s.outputs)

    def run_stage(self, s: dag.Stage, force: bool = False) -> StageResult:
        key, input_hashes = self.stage_key(s)
        if not force and self.is_fresh(s, key):
            print(f"[pag] {s.name}: up to date, skipped", file=sys.stderr)
            return StageResult(s.name, "skipped")
        inputs: dict[str, Any] = {}
        for name in s.inputs + s.optional_inputs:
            ds, path = dataset(name), self._input_path(name)
            if not path.exists():
                continue
            inputs[name] = io.read_table(path, ds.schema) if ds.kind == "table" else path
        staging = {o: io.staging_dir(self._input_path(o)) for o in s.outputs if dataset(o).kind == "dir"}
        run_cfg = self.config["run"]
        resume = self.resume_root / s.name
        if resume.is_dir():  # finished work of an interrupted run with other code, config or inputs
            for old in resume.iterdir():
                if old.name != key:
                    shutil.rmtree(old, ignore_errors=True)
        ctx = StageContext(stage=s.name, seq=self.seq, data_root=self.data_root, staging=staging,
                           show_progress=self.show_progress, progress_interval_s=run_cfg.progress_interval_s,
                           device=torch_device(run_cfg.device), scheduler=run_cfg.scheduler or None,
                           resume_dir=resume / key)
        print(f"[pag] {s.name}: running", file=sys.stderr)
        release_freed()  # the last stage's freed heap is not counted in this one's peak, nor held through it
        t0 = time.perf_counter()
        memory = PeakMemory().start()  # this process and its workers
        try:
            outputs = s.module.run(inputs, self.config[s.name], ctx)
            tables = [o for o in s.outputs if dataset(o).kind == "table"]
            if not isinstance(outputs, dict) or sorted(outputs) != sorted(tables):
                got = sorted(outputs) if isinstance(outputs, dict) else type(outputs).__name__
                raise PipelineError(f"stage {s.name!r} returned {got}, expected tables {sorted(tables)}")
            for name in tables:
                if not isinstance(outputs[name], pd.DataFrame):
                    raise PipelineError(f"stage {s.name!r} returned {type(outputs[name]).__name__} for {name!r}")
                io.write_table(outputs[name], self._input_path(name), dataset(name).schema,
                               metadata={"pag.stage": s.name, "pag.seq": self.seq,
                                         "pag.commit": provenance.code_version()})
            for name, path in staging.items():
                io.swap_dir(path, self._input_path(name))
        except Exception:
            for path in staging.values():
                shutil.rmtree(path, ignore_errors=True)
            raise
        finally:
            memory.stop()
        seconds = time.perf_counter() - t0
        record = {"stage": s.name, "key": key, "seconds": round(seconds, 3),
                  "peak_rss_mb": round(memory.peak_mb, 1), "inputs": input_hashes,
                  "outputs": {o: self.hashes.tree_hash(self._input_path(o)) for o in s.outputs},
                  "config": cfgmod.to_dict(self.config[s.name]), "summary": ctx.summary,
                  "finished_unix": time.time(), "code_version": provenance.code_version()}
        io.atomic_write_bytes(self.manifest_path(s), json.dumps(record, indent=1, default=str).encode())
        self.hashes.save()
        shutil.rmtree(resume, ignore_errors=True)  # the outputs are committed: partial work is not needed
        with contextlib.suppress(OSError):
            self.resume_root.rmdir()  # only when empty
        brief = ", ".join(f"{k}={v}" for k, v in ctx.summary.items() if k != "notes")
        print(f"[pag] {s.name}: done in {seconds:.1f} s" + (f" ({brief})" if brief else ""), file=sys.stderr)
        for note in ctx.summary.get("notes", []):
            print(f"[pag] {s.name}: {note}", file=sys.stderr)
        return StageResult(s.name, "ran", seconds, ctx.summary, memory.peak_mb)
