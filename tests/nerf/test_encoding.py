import os
import subprocess
import sys
import warnings
from pathlib import Path

import pytest
import torch

from nerf import _ext, encoding
from nerf.encoding import (CubicHashEncoding, PermutoEncoding, cubic_encode_reference, lattice, permuto_coefficients,
                           permuto_encode_reference, simplex)

ROOT = Path(__file__).resolve().parents[2]
KW = dict(n_levels=8, n_features=2, log2_capacity=10, coarsest_scale=1.0, finest_scale=0.01, init_std=1.0)


def fused_ext():
    ext = _ext.load_permuto_ext("cpu")
    if ext is None:
        pytest.skip("no C++ toolchain here: the fused kernel is unavailable")
    return ext


def points(n=400, seed=0):
    """Random points, lines along each lattice axis (through 0, i.e. on coordinate planes), and
    points far outside [-1, 1]^3."""
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(n, 3, generator=g) * 2 - 1
    t = torch.linspace(-1, 1, 41)
    lines = [torch.zeros(41, 3) for _ in range(3)]
    for i, line in enumerate(lines):
        line[:, i] = t
    far = torch.tensor([[40.0, -30.0, 25.0], [-7.5, 12.0, 3.0], [900.0, -900.0, 0.5], [-1e3, 1e3, 1e3]])
    return torch.cat([x, *lines, far])


def pair(cls, **overrides):
    kw = KW | overrides
    fused, ref = cls(**kw, backend="fused"), cls(**kw, backend="torch")
    ref.load_state_dict(fused.state_dict())
    return fused, ref


def rel_err(a, b):
    a, b = a.detach(), b.detach()
    return float((a - b).abs().max() / b.abs().max().clamp_min(1e-30))


@pytest.mark.parametrize("cls", [PermutoEncoding, CubicHashEncoding])
@pytest.mark.parametrize("levels,features", [(8, 2), (24, 2), (4, 1), (3, 3), (2, 8), (2, 11)])
@pytest.mark.parametrize("jacobian_in_forward", [True, False])
def test_fused_equals_reference_in_values_and_both_gradients(cls, levels, features, jacobian_in_forward, monkeypatch):
    fused_ext()
    monkeypatch.setattr(encoding, "JACOBIAN_IN_FORWARD", jacobian_in_forward)
    fused, ref = pair(cls, n_levels=levels, n_features=features, finest_scale=1e-3)
    x1 = points().requires_grad_()
    x2 = x1.detach().clone().requires_grad_()
    a, b = fused(x1), ref(x2)
    assert a.shape == (len(x1), levels * features)
    assert rel_err(a, b) < 1e-5
    g = torch.randn_like(a)
    a.backward(g)
    b.backward(g)
    assert rel_err(fused.table.grad, ref.table.grad) < 1e-5
    assert rel_err(x1.grad, x2.grad) < 1e-5
    # and per point: the position gradients agree everywhere, not just at the largest one
    scale = x2.grad.abs().amax(1, keepdim=True).clamp_min(1e-3)
    assert float(((x1.grad - x2.grad).abs() / scale).max()) < 1e-3


@pytest.mark.parametrize("cls", [PermutoEncoding, CubicHashEncoding])
def test_fused_gradients_one_at_a_time(cls):
    """Table gradients alone (x without grad: no Jacobian is made) and position gradients alone."""
    fused_ext()
    fused, ref = pair(cls)
    x = points()
    fused(x).square().sum().backward()
    ref(x).square().sum().backward()
    assert rel_err(fused.table.grad, ref.table.grad) < 1e-5
    for enc in (fused, ref):
        enc.table.requires_grad_(False)
    x1, x2 = x.clone().requires_grad_(), x.clone().requires_grad_()
    fused(x1).square().sum().backward()
    ref(x2).square().sum().backward()
    assert rel_err(x1.grad, x2.grad) < 1e-5


def test_kernel_simplices_equal_the_reference_and_are_barycentric():
    ext = fused_ext()
    x = points(2000)
    coef = permuto_coefficients(torch.tensor([0.05]))
    shift = torch.tensor([[0.1, 0.2, 0.3]])
    rows, w = ext.permuto_simplices(x, coef[0], shift[0], 1024)
    ref_rows, ref_w = lattice(x, coef, shift, 1023)
    assert torch.equal(rows, ref_rows[0]) and torch.equal(w, ref_w[0])  # bit-identical lattice arithmetic
    assert torch.allclose(w.sum(1), torch.ones(len(w)), atol=1e-5)
    assert (w >= -1e-6).all() and (w <= 1 + 1e-6).all()
    assert rows.min() >= 0 and rows.max() < 1024


def test_simplex_vertices_enclose_the_point():
    """In float64: the 4 vertices lie on the plane sum = 0, vertex k has every coordinate = k (mod 4),
    and the barycentric combination of the vertices is the elevated point itself."""
    g = torch.Generator().manual_seed(1)
    x = (torch.rand(5000, 3, generator=g) * 6 - 3).double()
    scales = torch.tensor([1.0, 0.1, 0.003], dtype=torch.float64)
    e, keys, w = simplex(x, permuto_coefficients(scales), torch.rand(3, 3, generator=g).double())
    assert (keys.sum(-1) == 0).all()
    assert ((keys - torch.arange(4)[:, None]) % 4 == 0).all()
    assert torch.allclose((w[..., None] * keys).sum(-2), e, atol=1e-9)
    assert (w >= -1e-12).all() and torch.allclose(w.sum(-1), torch.ones_like(w[..., 0]))


@pytest.mark.parametrize("backend", ["torch", "fused"])
def test_features_are_continuous_across_simplex_boundaries(backend):
    if backend == "fused":
        fused_ext()
    enc = PermutoEncoding(n_levels=1, log2_capacity=12, coarsest_scale=0.05, finest_scale=0.05, init_std=1.0,
                          backend=backend)
    step = 2e-5
    t = torch.arange(0, 25000, dtype=torch.float32)[:, None] * step
    line = torch.tensor([[-0.3, 0.2, 0.1]]) + t * torch.tensor([[0.6, -0.48, 0.64]])  # unit direction
    rows, _ = lattice(line, permuto_coefficients(enc.scales), enc.shifts, enc.rows[0] - 1)
    crossing = (rows[0, 1:].sort(1).values != rows[0, :-1].sort(1).values).any(1)
    assert crossing.sum() > 5  # the line does pass through several simplices
    with torch.no_grad():
        jump = (enc(line[1:]) - enc(line[:-1])).abs().amax(1)
    # inside a simplex the features are linear: the steps there bound the slope
    assert jump[crossing].max() <= 1.5 * jump[~crossing].max() + 1e-6


def test_reference_gradcheck_in_double():
    enc = PermutoEncoding(n_levels=2, log2_capacity=6, finest_scale=0.3, init_std=1.0, backend="torch").double()
    g = torch.Generator().manual_seed(0)
    x = (torch.rand(6, 3, generator=g, dtype=torch.float64) - 0.5).requires_grad_()
    table = enc.table.detach().clone().requires_grad_()
    for ref in (permuto_encode_reference, cubic_encode_reference):
        assert torch.autograd.gradcheck(lambda p, t: ref(p, t, enc.offsets, enc.scales, enc.shifts), (x, table),
                                        eps=1e-6, atol=1e-5)


@pytest.mark.parametrize("cls", [PermutoEncoding, CubicHashEncoding])
def test_thread_count_does_not_change_results(cls):
    fused_ext()
    enc = cls(**KW, backend="fused")
    x = points()
    before = torch.get_num_threads()
    outs = []
    try:
        for n in (1, 2, 3):
            torch.set_num_threads(n)
            xx = x.clone().requires_grad_()
            y = enc(xx)
            y.square().sum().backward()
            outs.append((y.detach(), enc.table.grad.clone(), xx.grad))
            enc.table.grad = None
    finally:
        torch.set_num_threads(before)
    for y, gt, gx in outs[1:]:
        assert torch.equal(y, outs[0][0]) and torch.equal(gt, outs[0][1])  # one writer per level: deterministic
        assert rel_err(gx, outs[0][2]) < 1e-6  # only the order of the per-level sums differs


@pytest.mark.parametrize("cls", [PermutoEncoding, CubicHashEncoding])
def test_levels_with_fewer_rows_match_the_reference_and_use_only_their_rows(cls):
    fused_ext()
    rows = [16, 64, 1024, 256, 1024, 32, 1024, 1024]
    fused, ref = (cls(**KW, backend=b) for b in ("fused", "torch"))
    for enc in (fused, ref):
        enc.set_rows(rows)
    ref.load_state_dict(fused.state_dict())
    assert fused.rows == rows and fused.table.shape == (sum(rows), KW["n_features"])
    x1 = points().requires_grad_()
    x2 = x1.detach().clone().requires_grad_()
    a, b = fused(x1), ref(x2)
    assert rel_err(a, b) < 1e-5
    g = torch.randn_like(a)
    a.backward(g)
    b.backward(g)
    assert rel_err(fused.table.grad, ref.table.grad) < 1e-5 and rel_err(x1.grad, x2.grad) < 1e-5
    # each level reads its own rows: a level's features depend on its slice of the table and on nothing else
    lvl, f = 1, KW["n_features"]
    with torch.no_grad():
        fused.table[sum(rows[:lvl]):sum(rows[:lvl + 1])] += 1.0
    moved = (fused(x1) - a).detach().abs().amax(0).reshape(len(rows), f).amax(1)
    assert moved[lvl] > 0.5 and float(moved[torch.arange(len(rows)) != lvl].max()) == 0.0


def test_size_levels_gives_coarse_levels_the_rows_their_vertices_use():
    enc = PermutoEncoding(n_levels=6, n_features=2, log2_capacity=16, coarsest_scale=0.5, finest_scale=0.002)
    g = torch.Generator().manual_seed(0)
    surface = torch.rand(20000, 3, generator=g) * torch.tensor([0.4, 0.4, 0.0]) - 0.2  # a 0.4 x 0.4 square
    touched = enc.touched_rows(surface)
    assert touched == sorted(touched) and touched[0] < 20 and touched[-1] > 5000  # coarse levels: few vertices
    ref = PermutoEncoding(n_levels=6, n_features=2, log2_capacity=16, coarsest_scale=0.5, finest_scale=0.002,
                          backend="torch")
    assert ref.touched_rows(surface) == touched   # the kernel's simplices (where built) count what the reference does
    rows = enc.size_levels(surface, headroom=32)
    assert enc.rows == rows and enc.table.shape[0] == sum(rows)
    for n, r in zip(touched, rows):  # a power of two from 32x to 64x the vertices, or the whole capacity
        assert r & (r - 1) == 0 and (32 * n <= r < 64 * n or r == 2 ** 16)
    assert rows[0] < 2 ** 10 and rows[-1] == 2 ** 16
    assert enc.size_levels(torch.zeros(0, 3)) == rows  # no points: the rows stay


def test_rows_per_level_come_with_the_state_and_old_tables_load():
    enc = PermutoEncoding(**KW)
    enc.set_rows([16, 32, 64, 128, 256, 512, 1024, 1024])
    x = points()
    other = PermutoEncoding(**KW)
    other.load_state_dict(enc.state_dict())
    assert other.rows == enc.rows and torch.equal(other(x), enc(x))
    # a table from before per-level rows, [L, T, F]: L levels of T rows, the same features
    full = PermutoEncoding(**KW)
    old = {k: v for k, v in full.state_dict().items() if k != "offsets"}
    old["table"] = old["table"].reshape(KW["n_levels"], -1, KW["n_features"])
    enc.load_state_dict(old)
    assert enc.rows == [2 ** KW["log2_capacity"]] * KW["n_levels"] and torch.equal(enc(x), full(x))


def test_full_capacity_table_draws_the_numbers_of_a_level_by_level_table():
    enc = PermutoEncoding(**KW)
    g = torch.Generator().manual_seed(0)
    torch.rand(KW["n_levels"], 3, generator=g)
    want = torch.randn(KW["n_levels"], 2 ** KW["log2_capacity"], KW["n_features"], generator=g) * KW["init_std"]
    assert torch.equal(enc.table.detach(), want.reshape(-1, KW["n_features"]))


def test_empty_batch():
    fused_ext()
    for backend in ("fused", "torch"):
        enc = PermutoEncoding(**KW, backend=backend)
        x = torch.zeros(0, 3, requires_grad=True)
        y = enc(x)
        y.sum().backward()
        assert y.shape == (0, enc.out_dim) and x.grad.shape == (0, 3)


def test_rejects_bad_input_and_settings():
    enc = PermutoEncoding(**KW)
    with pytest.raises(ValueError, match=r"expected positions \[N, 3\]"):
        enc(torch.zeros(5, 2))
    with pytest.raises(ValueError, match="finest_scale"):
        PermutoEncoding(coarsest_scale=0.01, finest_scale=0.1)
    with pytest.raises(ValueError, match="backend"):
        PermutoEncoding(backend="cuda")


def test_fallback_warns_once_and_still_works(monkeypatch):
    monkeypatch.setattr(_ext, "_CACHE", {})

    def broken_build(device_type):
        raise OSError("no compiler")

    monkeypatch.setattr(_ext, "_build", broken_build)
    enc = PermutoEncoding(**KW)
    ref = PermutoEncoding(**KW, backend="torch")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        out1 = enc(points())
        out2 = enc(points())
    msgs = [w for w in caught if "fused permutohedral kernel unavailable" in str(w.message)]
    assert len(msgs) == 1 and "no compiler" in str(msgs[0].message)
    assert torch.equal(out1, out2) and torch.equal(out1, ref(points()))
    with pytest.raises(RuntimeError, match="fused kernel is unavailable"):
        PermutoEncoding(**KW, backend="fused")(points())


def test_pag_no_ext_forces_the_reference(monkeypatch):
    monkeypatch.setenv("PAG_NO_EXT", "1")
    assert _ext.load_permuto_ext("cpu") is None
    x = points().requires_grad_()
    y = PermutoEncoding(**KW)(x)
    y.sum().backward()
    assert torch.isfinite(x.grad).all()
    with pytest.raises(RuntimeError, match="PAG_NO_EXT"):
        PermutoEncoding(**KW, backend="fused")(x)


@pytest.mark.parametrize("backend", ["torch", "auto"])
def test_half_precision_autocast_and_huge_coordinates_stay_finite(backend):
    enc = PermutoEncoding(**KW, backend=backend)
    x = (points() * 3).half()
    with torch.autocast("cpu", dtype=torch.bfloat16):
        y = enc(x)
    assert y.dtype == torch.float32 and torch.isfinite(y).all()
    x = torch.tensor([[float("nan"), float("inf"), -1e30], [1e4, 1e4, -1e4], [-1e4, 3e3, 0.2]], requires_grad=True)
    y = enc(x)
    y.square().sum().backward()
    assert torch.isfinite(y).all() and torch.isfinite(enc.table.grad).all() and torch.isfinite(x.grad).all()


@pytest.mark.parametrize("cls", [PermutoEncoding, CubicHashEncoding])
def test_fused_clamps_like_the_reference(cls):
    """The CPU kernel clamps x itself (NaN -> 0, +-inf and beyond the bound -> +-bound): values and both
    gradients as the reference's torch.nan_to_num + clamp give, position gradients 0 where clamped."""
    fused_ext()
    fused, ref = pair(cls)
    b = fused.bound
    x = torch.tensor([[float("nan"), 0.3, -0.2], [float("inf"), -float("inf"), 0.1], [2 * b, -0.5, 0.25],
                      [b, -b, 0.7], [0.05, -3 * b, 0.6], [0.1, 0.2, 0.3]])
    x1, x2 = x.clone().requires_grad_(), x.clone().requires_grad_()
    a, r = fused(x1), ref(x2)
    assert rel_err(a, r) < 1e-5
    g = torch.randn_like(a)
    a.backward(g)
    r.backward(g)
    assert rel_err(fused.table.grad, ref.table.grad) < 1e-5
    assert torch.isfinite(x1.grad).all()
    assert float((x1.grad - x2.grad).abs().max()) <= 1e-5 * float(x2.grad.abs().max())
    clamped = ~((x >= -b) & (x <= b))
    assert bool((x1.grad[clamped] == 0).all()) and bool((x1.grad[~clamped] != 0).any())


@pytest.mark.parametrize("env", [{"PAG_NO_AVX2": "1"}, {"PAG_NO_AVX512": "1"}], ids=["baseline", "avx2"])
def test_narrower_x86_builds_match_the_reference(env):
    """The kernels are compiled three times (baseline x86-64, AVX2, AVX-512, the widest the CPU runs
    picked at run time); run the narrower ones in a subprocess so that each is held to the reference,
    its lattice arithmetic bit for bit."""
    fused_ext()
    code = ("import torch\n"
            "from nerf._ext import load_permuto_ext\n"
            "from nerf.encoding import PermutoEncoding, CubicHashEncoding, lattice, permuto_coefficients\n"
            "x = torch.rand(2000, 3) * 2 - 1\n"
            "coef, shift = permuto_coefficients(torch.tensor([0.05])), torch.tensor([[0.1, 0.2, 0.3]])\n"
            "rows, w = load_permuto_ext('cpu').permuto_simplices(x, coef[0], shift[0], 1024)\n"
            "ref_rows, ref_w = lattice(x, coef, shift, 1023)\n"
            "assert torch.equal(rows, ref_rows[0]) and torch.equal(w, ref_w[0])\n"
            "for cls in (PermutoEncoding, CubicHashEncoding):\n"
            "    kw = dict(n_levels=6, log2_capacity=10, finest_scale=0.01, init_std=1.0)\n"
            "    f, r = cls(**kw, backend='fused'), cls(**kw, backend='torch')\n"
            "    x1 = (torch.rand(300, 3) * 2 - 1).requires_grad_(); x2 = x1.detach().clone().requires_grad_()\n"
            "    a, b = f(x1), r(x2); a.sum().backward(); b.sum().backward()\n"
            "    assert torch.allclose(a, b, atol=1e-5), cls\n"
            "    assert torch.allclose(f.table.grad, r.table.grad, atol=1e-5), cls\n"
            "    assert torch.allclose(x1.grad, x2.grad, rtol=1e-4, atol=1e-3), cls\n"
            "print('ok')\n")
    env = os.environ | env | {"PYTHONPATH": str(ROOT)}
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, cwd=ROOT, timeout=600)
    assert done.returncode == 0 and "ok" in done.stdout, done.stderr[-2000:]


@pytest.mark.cuda
@pytest.mark.parametrize("cls", [PermutoEncoding, CubicHashEncoding])
def test_cuda_matches_cpu_reference(cls):
    cpu = cls(**KW, backend="torch")
    cpu.set_rows([16, 64, 1024, 256, 1024, 32, 1024, 1024])   # levels of their own sizes
    gpu = cls(**KW, backend="auto").cuda()
    gpu.load_state_dict(cpu.state_dict())
    x = points()
    x1, x2 = x.clone().requires_grad_(), x.cuda().requires_grad_()
    a, b = cpu(x1), gpu(x2)
    assert torch.allclose(a, b.cpu(), rtol=1e-4, atol=1e-4)
    g = torch.randn_like(a)
    a.backward(g)
    b.backward(g.cuda())
    assert torch.allclose(cpu.table.grad, gpu.table.grad.cpu(), rtol=1e-4, atol=1e-4)
    assert rel_err(x2.grad.cpu(), x1.grad) < 1e-4


def test_bench_encoding_runs_on_a_tiny_problem(tmp_path):
    fused_ext()
    from bench import encoding as bench_encoding

    df = bench_encoding.run(n_points=300, n_levels=2, n_features=2, log2_capacity=8, repeats=1, threads=1,
                            out_dir=tmp_path)
    assert (tmp_path / "encoding.parquet").exists() and (tmp_path / "encoding.png").exists()
    assert set(df.variant) == {"permuto_torch", "permuto_fused", "cubic_torch", "cubic_fused", "mem_4r", "mem_4r4u"}
    assert len(df) == 2 * 2 * 6 and (df.mpts_per_s > 0).all()
    fused = df[df.variant == "permuto_fused"]
    assert fused.speedup_vs_torch.notna().all() and fused.speedup_vs_cubic.notna().all()
