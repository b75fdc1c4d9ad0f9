import pytest

from pipeline import dag
from fake_stages import make


def noop(inputs, cfg, ctx):
    return {}


def test_duplicate_output_names_both_producers():
    a = make("a", [], ["windows"], noop)
    b = make("b", [], ["windows"], noop)
    with pytest.raises(dag.DagError, match="'windows' is produced by both 'a' and 'b'"):
        dag.check([a, b])


def test_cycle_is_reported_with_stage_names():
    a = make("a", ["frames"], ["windows"], noop)
    b = make("b", ["windows"], ["frames"], noop)
    with pytest.raises(dag.DagError, match="cycle among stages"):
        dag.check([a, b])


def test_missing_producer_and_unknown_dataset():
    with pytest.raises(dag.DagError, match="needs 'frames' but no stage produces it"):
        dag.check([make("a", ["frames"], ["windows"], noop)])
    with pytest.raises(dag.DagError, match="not in the catalog"):
        dag.check([make("a", [], ["nonsense"], noop)])


def test_order_follows_data_not_declaration():
    b = make("b", ["windows"], ["window_poses"], noop)
    a = make("a", ["raw"], ["windows"], noop)
    order = [s.name for s in dag.check([b, a])]
    assert order == ["a", "b"]
    assert dag.downstream(dag.check([b, a]), "a") == ["b"]


def test_stage_order_is_readable_without_heavy_imports():
    import subprocess
    import sys
    code = "import sys; from pipeline.dag import STAGE_ORDER; assert 'torch' not in sys.modules; print(*STAGE_ORDER)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split()[:2] == ["synth", "ingest"]
