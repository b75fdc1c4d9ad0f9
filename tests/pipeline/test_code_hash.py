"""The manifest's code hash: what a stage imports, transitively, as parsed code without docstrings."""
import ast
import shutil
import textwrap
from pathlib import Path

import pytest

from pipeline import codehash, dag, runner
from pipeline.runner import Runner



@pytest.fixture(scope="module")
def stages():
    return dag.build()


@pytest.fixture
def tree(tmp_path, monkeypatch):
    """A copy of the project's packages; the runner resolves modules there, so edits leave the repo alone."""
    for init in runner.REPO_ROOT.glob("*/__init__.py"):
        pkg = init.parent.name
        shutil.copytree(runner.REPO_ROOT / pkg, tmp_path / pkg, ignore=shutil.ignore_patterns("__pycache__"))
    monkeypatch.setattr(runner, "REPO_ROOT", tmp_path)
    return tmp_path


def hashes(stages) -> dict[str, str]:
    return {s.name: runner.code_hash(s) for s in stages}


def insert_into_function(path: Path, func: str, line: str) -> None:
    """Put `line` as the first statement of `func`'s body (after its docstring)."""
    src = path.read_text().splitlines(keepends=True)
    fn = next(n for n in ast.walk(ast.parse("".join(src))) if isinstance(n, ast.FunctionDef) and n.name == func)
    first = fn.body[1] if isinstance(fn.body[0], ast.Expr) and len(fn.body) > 1 else fn.body[0]
    indent = src[first.lineno - 1][: first.col_offset]
    src.insert(first.lineno - 1, f"{indent}{line}\n")
    path.write_text("".join(src))


def importers(stages, module: str) -> set[str]:
    """Stages whose import closure holds `module`."""
    root = runner.REPO_ROOT
    return {s.name for s in stages
            if module in codehash.closure({s.module.__name__: codehash.module_file(s.module.__name__, root)}, root)}


def test_a_helper_edit_in_pipeline_images_changes_exactly_the_stages_that_import_it(tree, stages):
    before = hashes(stages)
    insert_into_function(tree / "pipeline" / "images.py", "read_label", "_unused = 0")
    after = hashes(stages)
    changed = {n for n in before if before[n] != after[n]}
    assert changed == importers(stages, "pipeline.images")
    # windows and colmap_poses read no image: they keep their hash; the stages reading labels do not
    assert {"windows", "colmap_poses"}.isdisjoint(changed)
    assert {"depth_filter", "ingest", "nerf_fit", "fruit_count", "evaluate"} <= changed


def test_docstring_and_comment_edits_in_nerf_change_no_hash(tree, stages):
    before = hashes(stages)
    cfg = tree / "nerf" / "config.py"
    text = cfg.read_text()
    mod = ast.parse(text)
    doc = ast.get_docstring(mod)
    text = text.replace(doc, doc + "\n\nA new paragraph of the module docstring.", 1)
    cls = next(n for n in mod.body if isinstance(n, ast.ClassDef))
    field_doc = next(s.value.value for s in cls.body[1:] if isinstance(s, ast.Expr) and isinstance(s.value, ast.Constant))
    text = text.replace(field_doc, field_doc + " (edited)", 1)
    cfg.write_text(text + "\n# a trailing comment\n\n")
    render = tree / "nerf" / "render.py"
    render.write_text("# a comment at the top\n" + render.read_text().replace("\n\n\n", "\n\n\n# between functions\n", 1))
    real = Path(runner.__file__).resolve().parents[1]
    assert cfg.read_text() != (real / "nerf" / "config.py").read_text()
    assert hashes(stages) == before


def test_a_code_edit_in_nerf_changes_nerf_fit_and_no_stage_before_it(tree, stages):
    before = hashes(stages)
    insert_into_function(tree / "nerf" / "render.py", "composite_weights", "_unused = 0")
    after = hashes(stages)
    changed = {n for n in before if before[n] != after[n]}
    assert "nerf_fit" in changed
    upstream = {"synth", "ingest", "depth_filter", "windows", "colmap_poses"}
    assert upstream.isdisjoint(changed)
    assert changed == importers(stages, "nerf.render")


def test_native_sources_count_for_stages_that_load_the_extension(tree, stages):
    before = hashes(stages)
    src = next(p for p in sorted((tree / "nerf" / "csrc").iterdir()) if p.suffix == ".cpp")
    src.write_text(src.read_text() + "\n// edited\n")
    after = hashes(stages)
    changed = {n for n in before if before[n] != after[n]}
    assert changed == importers(stages, "nerf._ext") and "nerf_fit" in changed


def test_imports_are_resolved_relative_absolute_and_from_packages(tmp_path):
    pkg = tmp_path / "pkg"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "sub" / "__init__.py").write_text("from . import leaf\n")
    (pkg / "sub" / "leaf.py").write_text("from ..util import helper\n")
    (pkg / "util.py").write_text("def helper():\n    return 1\n")
    (pkg / "lonely.py").write_text("X = 1\n")
    (pkg / "start.py").write_text("def f():\n    from pkg.sub import leaf\n    import numpy\n    return leaf\n")
    found = codehash.closure({"pkg.start": pkg / "start.py"}, tmp_path)
    assert set(found) == {"pkg", "pkg.start", "pkg.sub", "pkg.sub.leaf", "pkg.util"}
    h0 = codehash.code_hash(["pkg.start"], tmp_path)
    (pkg / "lonely.py").write_text("X = 2\n")             # not imported: no change
    assert codehash.code_hash(["pkg.start"], tmp_path) == h0
    (pkg / "util.py").write_text('def helper():\n    """Now documented."""\n    return 1  # one\n')
    assert codehash.code_hash(["pkg.start"], tmp_path) == h0
    (pkg / "util.py").write_text("def helper():\n    return 2\n")
    assert codehash.code_hash(["pkg.start"], tmp_path) != h0


FIRST = '''
from dataclasses import dataclass

import pandas as pd

from fakelib.helper import scale

INPUTS, OUTPUTS = (), ("windows", "images")


@dataclass(frozen=True)
class Config:
    value: int = 1
    """a knob."""


def run(inputs, cfg, ctx):
    (ctx.output_dir("images") / "a.txt").write_text("x")
    n = 3
    return {"windows": pd.DataFrame({"window_id": [0] * n, "frame_id": list(range(n)), "center_frame_id": [0] * n,
                                     "offset": list(range(n)), "split": ["train"] * n, "is_center": [False] * n,
                                     "n_windows": [scale(1)] * n})}
'''

SECOND = '''
from dataclasses import dataclass

import pandas as pd

INPUTS, OUTPUTS = ("windows",), ("gt_segments",)


@dataclass(frozen=True)
class Config:
    value: int = 1
    """a knob."""


def run(inputs, cfg, ctx):
    w = inputs["windows"]
    return {"gt_segments": pd.DataFrame({"frame_id": w["frame_id"], "instance_id": w["n_windows"], "class_id": 2,
                                         "area_px": 10, "near_depth_frac": 1.0, "kept": True, "drop_reason": ""})}
'''


def test_the_runner_reruns_a_stage_when_a_module_it_imports_changes(tmp_path, monkeypatch):
    import importlib

    code = tmp_path / "code"
    for pkg, files in {"fakestages": {"first.py": FIRST, "second.py": SECOND},
                       "fakelib": {"helper.py": 'def scale(v):\n    """Times one."""\n    return v\n'}}.items():
        (code / pkg).mkdir(parents=True)
        (code / pkg / "__init__.py").write_text("")
        for name, text in files.items():
            (code / pkg / name).write_text(textwrap.dedent(text))
    monkeypatch.syspath_prepend(str(code))
    monkeypatch.setattr(runner, "REPO_ROOT", code)
    stages = [dag.stage_from_module(n, importlib.import_module(f"fakestages.{n}")) for n in ("first", "second")]

    def statuses():
        return [r.status for r in Runner("seqA", data_root=tmp_path / "data", show_progress=False,
                                         stages=stages).run()]

    assert statuses() == ["ran", "ran"]
    assert statuses() == ["skipped", "skipped"]
    helper = code / "fakelib" / "helper.py"
    helper.write_text('def scale(v):\n    """Times one, documented again."""\n    # a comment\n    return v\n')
    assert statuses() == ["skipped", "skipped"]
    helper.write_text("def scale(v):\n    return v * 1\n")
    # first's code changed; its outputs did not, so second (which imports nothing of fakelib) stays
    assert statuses() == ["ran", "skipped"]
