"""run.device: 'auto' takes the GPU where torch sees one, else the CPU; a GPU that is not there is a clear error;
a local cluster on GPUs has one worker per GPU, and windows take the GPUs in turn. The GPUs are faked through
torch.cuda's queries, so this runs on any machine (tests/nerf/test_cuda.py runs the model on a real GPU)."""
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from pipeline import config as cfgmod
from pipeline import parallel
from pipeline.runner import PipelineError, torch_device

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture
def gpus(monkeypatch):
    def fake(n: int) -> None:
        monkeypatch.setattr(torch.cuda, "is_available", lambda: n > 0)
        monkeypatch.setattr(torch.cuda, "device_count", lambda: n)
    return fake


def test_auto_is_the_gpu_where_torch_sees_one_else_the_cpu(gpus):
    gpus(0)
    assert torch_device("auto") == "cpu" and torch_device("cpu") == "cpu"
    gpus(1)
    assert torch_device("auto") == "cuda" and torch_device("cuda:0") == "cuda:0"


def test_a_gpu_torch_does_not_see_is_an_error_that_says_what_to_do(gpus):
    gpus(0)
    with pytest.raises(PipelineError, match=r"run.device=cuda, but torch .* sees 0 CUDA device.*auto or cpu"):
        torch_device("cuda")
    gpus(2)
    with pytest.raises(PipelineError, match="sees 2 CUDA device"):
        torch_device("cuda:2")


def test_the_default_is_auto_and_other_names_are_refused():
    assert cfgmod.RunConfig().device == "auto"
    for bad in ("gpu", "cuda:x", "mps", ""):
        with pytest.raises(cfgmod.ConfigError, match="run.device must be"):
            cfgmod.RunConfig(device=bad)


def test_one_worker_per_gpu_and_windows_take_the_gpus_in_turn(gpus):
    gpus(2)
    assert parallel.default_workers(5, "cuda") == 2 and parallel.default_workers(1, "cuda") == 1
    assert parallel.default_workers(5, "cuda:1") == 1
    assert [parallel.spread_over_gpus("cuda", i) for i in range(3)] == ["cuda:0", "cuda:1", "cuda:0"]
    assert parallel.spread_over_gpus("cuda:1", 0) == "cuda:1" and parallel.spread_over_gpus("cpu", 3) == "cpu"
    gpus(1)
    assert parallel.spread_over_gpus("cuda", 3) == "cuda"
    assert parallel.default_workers(8, "cpu") == min(8, os.cpu_count())


def test_every_stage_loads_and_depth_icp_runs_where_open3d_does_not_import():
    # a GPU machine often has no Open3D wheels: the DAG loads, and ICP takes its numpy path
    code = ("import sys; sys.modules['open3d'] = None\n"   # `import open3d` now raises ImportError
            "import numpy as np\n"
            "from pipeline import dag; dag.build()\n"
            "from nerf import depth_poses as dp\n"
            "assert dp.icp_backend() == 'numpy'\n"
            "z = np.full((40, 60), 1.0, np.float32); z[10:30, 20:40] = 0.8\n"
            "k = np.array([50.0, 50.0, 30.0, 20.0])\n"
            "c = dp.depth_cloud(z, k, 1.5, 0.02)\n"
            "t, fit = dp.register(c, c, np.eye(4), 0.05, min_points=10)\n"
            "assert np.allclose(t, np.eye(4), atol=1e-6) and fit == 1.0, (t, fit)\n"
            "print('ok')\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=300,
                          env=os.environ | {"PYTHONPATH": str(ROOT)})
    assert done.returncode == 0 and "ok" in done.stdout, done.stderr[-2000:]
