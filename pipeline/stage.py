"""What a stage sees of the world: its StageContext.

A stage module (stages/<name>.py) declares INPUTS and OUTPUTS (dataset names from
pipeline/catalog.py), a frozen `Config` dataclass, and `run(inputs, cfg, ctx) -> dict[str, DataFrame]`.
`inputs` maps each declared input to a pandas DataFrame (tables) or a read-only Path (dirs).
The returned dict holds one DataFrame per declared table output. Files of a declared dir output are
written under `ctx.output_dir(name)`, a staging folder the runner swaps into place atomically
after the stage succeeds; `ctx.relpath(name, inner)` gives the path (relative to data/) such a file
will have afterwards, which is what tables store.
"""
from __future__ import annotations

import logging
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

from pipeline import progress as progressmod
from pipeline.catalog import dataset

T = TypeVar("T")
log = logging.getLogger("pag")


@dataclass
class StageContext:
    stage: str
    seq: str
    data_root: Path
    """The data/ folder; table paths are relative to it."""
    staging: dict[str, Path] = field(default_factory=dict)
    """Staging folder per dir output (filled by the runner)."""
    summary: dict[str, Any] = field(default_factory=dict)
    """Counts and notes the stage reports (skips, drops); printed and stored by the runner."""
    show_progress: bool = True
    progress_interval_s: float = 2.0
    """Least seconds between two progress lines of one task when stderr is not a terminal."""
    device: str = "cpu"
    scheduler: str | None = None
    """dask.distributed scheduler address, or None for a local cluster."""
    resume_dir: Path | None = None
    """A folder for finished units of work (e.g. one NeRF window) that must survive a killed run. The
    runner names it by the stage's key (code, config and input hashes), so what a stage finds there was
    made from exactly the same code, config and inputs; it deletes folders of other keys when the stage
    starts and this one once the stage's outputs are committed. A stage writes each unit atomically
    (build it under a temp name, rename it into place last) and reuses what it finds. Created on demand."""

    def output_dir(self, name: str) -> Path:
        if name not in self.staging:
            raise KeyError(f"stage {self.stage!r} did not declare dir output {name!r}; dir outputs: {sorted(self.staging)}")
        return self.staging[name]

    def relpath(self, name: str, inner: str | Path) -> str:
        """Path relative to data/ that `output_dir(name) / inner` will have once committed."""
        final = dataset(name).path(Path("."), self.seq) / inner
        return final.as_posix()

    def abspath(self, rel: str | Path) -> Path:
        """Absolute path of a table's relative path (files of committed datasets)."""
        return self.data_root / rel

    def raw_dir(self) -> Path:
        return dataset("raw").path(self.data_root, self.seq)

    def progress(self, it: Iterable[T], desc: str, total: int | None = None) -> Iterator[T]:
        """Iterate with progress on stderr (pipeline/progress.py: a bar on a terminal, else lines)."""
        return progressmod.iterate(it, self.stage, total, enabled=self.show_progress,
                                   interval_s=self.progress_interval_s, unit=desc)

    def count(self, key: str, n: int = 1) -> None:
        """Add to a counter in the stage summary (e.g. skipped frames by reason)."""
        self.summary[key] = self.summary.get(key, 0) + n

    def note(self, msg: str) -> None:
        self.summary.setdefault("notes", []).append(msg)
        log.info("%s: %s", self.stage, msg)
