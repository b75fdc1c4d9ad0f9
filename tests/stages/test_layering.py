"""The import layering of the stages: a stage imports library code, never another stage; the benchmarks and the
shared library import no stage either (they reach stages through the DAG and the runner)."""
import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def imported_modules(path: Path) -> set[str]:
    """Absolute names of the modules `path` imports (relative imports resolved within its package)."""
    package = path.parent.name
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                base = ".".join(filter(None, [package, base]))
            out.add(base)
            out |= {f"{base}.{a.name}" for a in node.names}
    return out


def stage_imports(path: Path) -> set[str]:
    return {m for m in imported_modules(path) if m == "stages" or m.startswith("stages.")}


@pytest.mark.parametrize("path", sorted((ROOT / "stages").glob("*.py")), ids=lambda p: p.name)
def test_no_stage_imports_another_stage(path):
    assert stage_imports(path) <= {"stages"} | ({f"stages.{path.stem}"} if path.stem != "__init__" else set())


@pytest.mark.parametrize("folder", ["bench", "rowmap", "pipeline", "nerf", "sources", "schemas", "synthetic"])
def test_libraries_and_benchmarks_import_no_stage(folder):
    offenders = {p.name: sorted(stage_imports(p)) for p in sorted((ROOT / folder).rglob("*.py")) if stage_imports(p)}
    assert offenders == {}


def test_the_check_sees_a_stage_import(tmp_path):
    (tmp_path / "stages").mkdir()
    bad = tmp_path / "stages" / "a.py"
    bad.write_text("def f():\n    from stages.b import helper\n    return helper\n")
    assert stage_imports(bad) == {"stages.b", "stages.b.helper"}
    rel = tmp_path / "stages" / "c.py"
    rel.write_text("from .b import helper\n")
    assert "stages.b" in stage_imports(rel)
