"""The stage DAG, declared once.

STAGE_ORDER is the only list of stages (the Makefile reads it with a plain `python3`, so this module
imports nothing heavy at import time). Each stage module declares its INPUTS and OUTPUTS by dataset
name; `build()` wires them and checks the graph: every input has exactly one producer (or is a
source dataset), no output is produced twice, no cycles.
"""
from __future__ import annotations

import importlib
from dataclasses import dataclass
from types import ModuleType

STAGE_ORDER: tuple[str, ...] = (
    "synth",
    "ingest",
    "depth_filter",
    "windows",
    "colmap_poses",
    "nerf_fit",
    "panoptic_fusion",
    "fruit_count",
    "evaluate",
    "report",
)

SOURCE_DATASETS: frozenset[str] = frozenset({"raw"})
"""Datasets that may exist without a producing stage (a recorded row placed under data/raw/)."""


class DagError(ValueError):
    """The declared stages do not form a valid DAG."""


@dataclass(frozen=True)
class Stage:
    name: str
    module: ModuleType
    inputs: tuple[str, ...]
    optional_inputs: tuple[str, ...]
    outputs: tuple[str, ...]

    @property
    def config_class(self) -> type:
        return self.module.Config


def load_stage(name: str) -> Stage:
    if name not in STAGE_ORDER:
        raise DagError(f"unknown stage {name!r}; stages: {list(STAGE_ORDER)}")
    return stage_from_module(name, importlib.import_module(f"stages.{name}"))


def stage_from_module(name: str, mod: ModuleType) -> Stage:
    for attr in ("INPUTS", "OUTPUTS", "Config", "run"):
        if not hasattr(mod, attr):
            raise DagError(f"stage module stages/{name}.py lacks {attr}")
    return Stage(name, mod, tuple(mod.INPUTS), tuple(getattr(mod, "OPTIONAL_INPUTS", ())), tuple(mod.OUTPUTS))


def build(names: tuple[str, ...] = STAGE_ORDER) -> list[Stage]:
    """Load and check the stages; returns them in a valid execution order."""
    return check([load_stage(n) for n in names])


def check(stages: list[Stage]) -> list[Stage]:
    """Check the wiring of `stages`; returns them in a valid execution order."""
    from pipeline.catalog import DATASETS

    producer: dict[str, str] = {}
    for s in stages:
        for out in s.outputs:
            if out not in DATASETS:
                raise DagError(f"stage {s.name!r} declares output {out!r} which is not in the catalog")
            if out in producer:
                raise DagError(f"dataset {out!r} is produced by both {producer[out]!r} and {s.name!r}")
            producer[out] = s.name
    for s in stages:
        for inp in s.inputs + s.optional_inputs:
            if inp not in DATASETS:
                raise DagError(f"stage {s.name!r} declares input {inp!r} which is not in the catalog")
        for inp in s.inputs:
            if inp not in producer and inp not in SOURCE_DATASETS:
                raise DagError(f"stage {s.name!r} needs {inp!r} but no stage produces it")
    order: list[Stage] = []
    placed: set[str] = set()
    pending = list(stages)
    while pending:
        ready = [s for s in pending
                 if all(producer[i] in placed for i in s.inputs + s.optional_inputs if i in producer)]
        if not ready:
            raise DagError(f"cycle among stages {[s.name for s in pending]}")
        for s in ready:
            order.append(s)
            placed.add(s.name)
            pending.remove(s)
    return order


def producers(stages: list[Stage]) -> dict[str, str]:
    return {out: s.name for s in stages for out in s.outputs}


def downstream(stages: list[Stage], name: str) -> list[str]:
    """Stages that (transitively) consume what `name` produces, in order."""
    affected = {name}
    out = []
    for s in stages:
        if s.name == name:
            continue
        ins = set(s.inputs + s.optional_inputs)
        if any(ins & set(t.outputs) for t in stages if t.name in affected):
            affected.add(s.name)
            out.append(s.name)
    return out
