"""Fixtures of the fruit-map tests: a tiny synthetic row run up to `windows` once per session, and copies of
it with NeRF outputs fabricated from ground truth (fruitmap_fixture.py)."""
from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import pytest
from fruitmap_fixture import SEQ, TINY, Row, SlotHook, copy_row, run_stages

from pipeline.runner import Runner


@pytest.fixture(scope="session")
def tiny_row_upstream(tmp_path_factory) -> Path:
    """data/ with the tiny row run through synth, ingest, depth_filter and windows (once per session)."""
    root = tmp_path_factory.mktemp("fruitmap") / "data"
    r = Runner(SEQ, data_root=root, overrides=TINY, show_progress=False)
    r.run(["synth", "ingest", "depth_filter", "windows"])
    return root


@pytest.fixture(scope="module")
def perfect_row(tiny_row_upstream, tmp_path_factory) -> Row:
    """Fabricated perfect renders, run through the four fruit-map stages (once per module)."""
    row = copy_row(tiny_row_upstream, tmp_path_factory.mktemp("perfect") / "data")
    run_stages(row)
    return row


@pytest.fixture()
def make_row(tiny_row_upstream, tmp_path) -> Callable[..., Row]:
    """make_row(seed=0, hook=None, name='data'): a fresh copy with fabricated NeRF outputs (stages not run)."""

    def make(seed: int = 0, hook: SlotHook | None = None, name: str = "data") -> Row:
        return copy_row(tiny_row_upstream, tmp_path / name, seed, hook)

    return make
