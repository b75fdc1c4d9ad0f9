import pytest

from pipeline import parallel


def square_or_fail(x):
    parallel.report(str(x), 1, 1, value=float(x))
    if x == 3:
        raise FloatingPointError("non-finite loss at step 7")
    return x * x


@pytest.mark.slow
def test_map_tasks_runs_all_and_keeps_failures_separate():
    out = parallel.map_tasks(square_or_fail, {str(i): i for i in range(4)}, n_workers=2, show_progress=False)
    assert {k: o.result for k, o in out.items() if o.error is None} == {"0": 0, "1": 1, "2": 4}
    assert isinstance(out["3"].error, FloatingPointError) and "step 7" in str(out["3"].error)
