"""Three windows on two workers: nerf_fit fits each window's colour phase and the rest of its fit as two tasks
(every colour phase first, so the third runs beside the others' panoptic phases). The split changes when
the work runs, not what it computes: the row ends with the outputs of one task per window."""
from __future__ import annotations

import pytest

from pipeline import cli, parallel
from test_killed_runs import TINY, assert_same_outputs

pytestmark = pytest.mark.slow  # two tiny rows of three windows each, about 60 s

SEQ = "synth_kill"   # assert_same_outputs compares this row
THREE_WINDOWS = [*TINY[:TINY.index("synth.n_labelled=2")], "synth.n_labelled=3",
                 *TINY[TINY.index("synth.n_labelled=2") + 1:], "--set", "nerf_fit.workers=2"]   # TINY has 1 worker


def run_row(root, monkeypatch, split: bool) -> list:
    """`pag all` on the row; returns the second parts map_tasks was given (None: one task per window)."""
    calls = []
    real = parallel.map_tasks

    def spy(fn, payloads, **kw):
        calls.append(kw.get("then"))
        return real(fn, payloads, **kw)

    with monkeypatch.context() as m:
        m.setattr(parallel, "map_tasks", spy)
        if not split:
            m.setattr(parallel, "own_cluster", lambda scheduler: False)
        assert cli.main(["all", "--seq", SEQ, "--data-root", str(root), "--no-progress", *THREE_WINDOWS]) == 0
    return calls


def test_the_colour_phases_as_tasks_of_their_own_give_the_same_row(tmp_path, monkeypatch):
    split, whole = tmp_path / "split" / "data", tmp_path / "whole" / "data"
    assert [t.__name__ if t else None for t in run_row(split, monkeypatch, split=True)] == ["fit_rest_part"]
    assert run_row(whole, monkeypatch, split=False) == [None]
    assert not list((split / "processed" / SEQ / "nerf").glob(".colour*"))   # the scratch files are gone
    assert_same_outputs(whole, split)
