"""The numerical stress suite at its fast size (`pag bench stress` runs the same case functions larger): every
case's checks pass, i.e. outputs and gradients stay finite and valid, bad inputs are refused clearly, and the
fused encoding kernel agrees with the pure-torch reference."""
import math

import pytest
import torch
from stress_cases import CASES, SIZES

from bench import stress
from nerf.panoptic.losses import instance_loss
from nerf.poses import rotation_6d
from nerf.render import composite_weights, cone_steps, exclusive_cumsum_per_ray

DEVICES = ["cpu", pytest.param("cuda", marks=pytest.mark.cuda)]


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("case", list(CASES))
def test_stress_case(case, device):
    checks = CASES[case](SIZES["fast"], device)
    assert checks, f"case {case} made no check"
    failed = [f"{c.component}: {c.detail}" for c in checks if not c.passed]
    assert not failed, "\n".join(failed)


def test_the_bench_runs_the_same_case_functions():
    assert stress.CASES == CASES


def test_bench_writes_the_table(tmp_path, monkeypatch):
    monkeypatch.setattr(stress, "CASES", {k: stress.CASES[k] for k in ("equal_costs", "degenerate_rotation_6d")})
    assert stress.main(["--size", "fast", "--out", str(tmp_path)]) == 0
    import pandas as pd

    df = pd.read_parquet(tmp_path / "stress.parquet")
    assert list(df.columns[:4]) == ["case", "component", "passed", "detail"] and df.passed.all()
    assert set(df.case) == {"equal_costs", "degenerate_rotation_6d"}


def test_a_failing_check_is_reported_not_hidden(monkeypatch):
    def broken(n, device):
        raise RuntimeError("boom")

    monkeypatch.setitem(stress.CASES, "broken", broken)
    checks = stress.run_case("broken", 8)
    assert [c.passed for c in checks] == [False] and "boom" in checks[0].detail


# -- the library bugs the suite found, pinned by small exact tests ------------------------------------
def test_compositing_of_a_ray_does_not_depend_on_the_rays_before_it():
    thin = torch.ones(8)
    alone, _ = composite_weights(thin, torch.full((8,), 0.05), torch.zeros(8, dtype=torch.long), 1)
    sigma = torch.cat([torch.full((4000 * 8,), 3.3e6), thin])
    ray = torch.arange(4001).repeat_interleave(8)
    w, _ = composite_weights(sigma, torch.full_like(sigma, 0.05), ray, 4001)
    assert torch.equal(w[-8:], alone)   # was off by 3 % through float32 cancellation


def test_exclusive_cumsum_per_ray_example_and_infinities():
    x = torch.tensor([1.0, 2.0, 3.0, math.inf, 5.0, 6.0])
    ray = torch.tensor([0, 0, 1, 2, 2, 2])
    assert exclusive_cumsum_per_ray(x, ray, 4).tolist() == [0.0, 1.0, 0.0, 0.0, math.inf, math.inf]


def test_zero_near_plane_is_refused_instead_of_looping_forever():
    with pytest.raises(ValueError, match="0 < near <= far"):
        cone_steps(0.0, 2.0, 0.01, torch.device("cpu"))


def test_degenerate_6d_inputs_give_rotations():
    a = torch.tensor([[0.0, 0, 0, 0, 0, 0], [1, 2, 3, 2, 4, 6], [1e30] * 6, [1e-30] * 6])
    r = rotation_6d(a)
    assert torch.allclose(r.transpose(1, 2) @ r, torch.eye(3).expand(4, 3, 3), atol=1e-6)
    assert torch.allclose(torch.linalg.det(r), torch.ones(4), atol=1e-6)
    assert torch.equal(r[0], torch.eye(3))
    # a regular input is unchanged by the guards: plain Gram-Schmidt
    b = torch.tensor([[2.0, 0, 0, 1, 3, 0]])
    assert torch.allclose(rotation_6d(b)[0], torch.eye(3))


def test_instance_loss_skips_rays_with_non_finite_weight():
    p = torch.tensor([[0.5, 0.5], [0.9, 0.1], [0.2, 0.8]])
    w = torch.tensor([1.0, math.nan, math.inf])
    got = instance_loss(p, torch.tensor([1, 0, 1]), w)
    assert torch.isclose(got, -torch.log(torch.tensor(0.5)))
