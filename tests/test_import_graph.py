"""The project's import graph: no circle among the modules of its packages (nerf, rowmap, sources, pipeline,
stages, schemas, synthetic, bench), and nothing in the model library nerf/ imports the layers above it."""
import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
ABOVE = ("pipeline", "stages", "bench", "rowmap", "synthetic", "sources", "schemas", "scripts")
PACKAGES = sorted(p.parent.name for p in ROOT.glob("*/__init__.py"))
"""Every package of the project (a top-level folder with an __init__.py)."""


def module_name(path: Path, root: Path = ROOT) -> str:
    parts = list(path.relative_to(root).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imports(path: Path, root: Path = ROOT) -> set[str]:
    """Absolute names of the modules `path` imports anywhere in it (function bodies included): for
    `from a.b import c`, 'a.b.c' when that is a module of the tree, else 'a.b'."""
    name = module_name(path, root)
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                up = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                base = ".".join(filter(None, [*up, base]))
            for a in node.names:
                sub = f"{base}.{a.name}"
                as_module = root.joinpath(*sub.split("."))
                out.add(sub if as_module.with_suffix(".py").is_file() or (as_module / "__init__.py").is_file() else base)
    return out


def graph(packages: str | list[str], root: Path = ROOT) -> dict[str, set[str]]:
    """module -> the modules of `packages` it imports (across packages too)."""
    names = [packages] if isinstance(packages, str) else packages
    mods = {module_name(p, root): p for package in names for p in sorted((root / package).rglob("*.py"))}
    return {m: {i for i in imports(p, root) if i in mods and i != m} for m, p in mods.items()}


def find_cycle(g: dict[str, set[str]]) -> list[str] | None:
    """One import circle of graph `g` as [a, b, ..., a], or None."""
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(m: str) -> list[str] | None:
        state[m] = 1
        stack.append(m)
        for n in sorted(g[m]):
            if state.get(n) == 1:
                return stack[stack.index(n):] + [n]
            if n not in state and (found := visit(n)):
                return found
        stack.pop()
        state[m] = 2
        return None

    for m in sorted(g):
        if m not in state and (found := visit(m)):
            return found
    return None


def test_the_project_has_no_import_circle():
    assert {"nerf", "rowmap", "sources", "pipeline", "stages", "schemas", "synthetic", "bench"} <= set(PACKAGES)
    assert find_cycle(graph(PACKAGES)) is None


def test_nerf_imports_nothing_above_it():
    offenders = {}
    for p in sorted((ROOT / "nerf").rglob("*.py")):
        bad = sorted(i for i in imports(p) if i.split(".")[0] in ABOVE)
        if bad:
            offenders[module_name(p)] = bad
    assert offenders == {}


def test_the_checks_see_a_circle_and_an_upward_import(tmp_path):
    pkg = tmp_path / "lib"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "sub" / "__init__.py").write_text("")
    (pkg / "a.py").write_text("from lib.sub import b\n")
    (pkg / "sub" / "b.py").write_text("def f():\n    from ..c import g\n    return g\n")
    (pkg / "c.py").write_text("import lib.a\nfrom stages.nerf_fit import run\n")
    g = graph("lib", tmp_path)
    assert g["lib.a"] == {"lib.sub.b"} and g["lib.sub.b"] == {"lib.c"}
    assert find_cycle(g) == ["lib.a", "lib.sub.b", "lib.c", "lib.a"]
    assert "stages.nerf_fit" in imports(pkg / "c.py", tmp_path)
    (pkg / "c.py").write_text("import math\n")
    assert find_cycle(graph("lib", tmp_path)) is None
    # a circle through two packages
    (tmp_path / "app").mkdir()
    (tmp_path / "app" / "__init__.py").write_text("")
    (tmp_path / "app" / "run.py").write_text("from lib import a\n")
    (pkg / "c.py").write_text("def f():\n    from app.run import a\n")
    assert find_cycle(graph("lib", tmp_path)) is None
    assert find_cycle(graph(["app", "lib"], tmp_path)) == ["app.run", "lib.a", "lib.sub.b", "lib.c", "app.run"]
