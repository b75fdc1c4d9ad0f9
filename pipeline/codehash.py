"""The code a stage's result depends on, as one hash: the project modules the stage imports, transitively.

A module's share is its parsed code (`ast.dump` of the tree, without line numbers) with every bare string
statement removed: comments vanish in the parse and docstrings are such statements, so neither a comment nor
a docstring edit changes the hash, while any change to what runs does. Imports are followed wherever they
are written (module level or inside a function): `import a.b`, `from a.b import c` (c as a submodule when
there is one), relative imports, and the `__init__` of every package on the way. Only modules under the
repository's own packages count; third-party code is pinned by the environment, not by this hash.

Compiled sources are code too: a module listed in NATIVE_SOURCES brings the bytes of the files its
extension loader compiles.
"""
from __future__ import annotations

import ast
import hashlib
from dataclasses import dataclass
from pathlib import Path

NATIVE_SOURCES: dict[str, tuple[str, tuple[str, ...]]] = {
    "nerf._ext": ("nerf/csrc", (".c", ".cc", ".cpp", ".cu", ".cuh", ".h", ".hpp")),
}
"""Module -> (folder under the repository root, file suffixes) of the C/C++/CUDA sources it compiles."""


@dataclass(frozen=True)
class ModuleCode:
    digest: str
    """hash of the module's parsed code without docstrings."""
    imports: tuple[str, ...]
    """absolute dotted names the module may import (resolved to files or dropped by the caller)."""


_PARSED: dict[tuple[str, bytes], ModuleCode] = {}
"""(module name, digest of the file's bytes) -> its ModuleCode; parsing is the slow part, reading is not."""


def strip_docstrings(tree: ast.AST) -> ast.AST:
    """`tree` with every statement that is a bare string constant removed (module, class and function
    docstrings, and the attribute docstrings under dataclass fields). Works in place; returns the tree."""
    for node in ast.walk(tree):
        body = getattr(node, "body", None)
        if isinstance(body, list):
            node.body = [s for s in body if not (isinstance(s, ast.Expr) and isinstance(s.value, ast.Constant)
                                                 and isinstance(s.value.value, str))]
    return tree


def imported_names(tree: ast.AST, module: str, is_package: bool) -> list[str]:
    """Absolute dotted names `module` imports: each imported module, its parent packages, and for
    `from x import y` also x.y (which is a module when y is a submodule)."""
    package = module if is_package else module.rpartition(".")[0]
    out: list[str] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                parts = package.split(".") if package else []
                base_parts = parts[: len(parts) - (node.level - 1)] if node.level - 1 <= len(parts) else []
                base = ".".join(base_parts + ([node.module] if node.module else []))
            else:
                base = node.module or ""
            if not base:
                continue
            out.append(base)
            out += [f"{base}.{a.name}" for a in node.names if a.name != "*"]
    full = []
    for name in out:
        parts = name.split(".")
        full += [".".join(parts[: i + 1]) for i in range(len(parts))]
    return full


def module_file(name: str, root: Path) -> Path | None:
    """The file of project module `name` under `root` (a package's __init__.py), or None when `name` is not
    a module of one of the repository's packages (third-party, standard library, or an attribute)."""
    parts = name.split(".")
    if not (root / parts[0] / "__init__.py").is_file():
        return None
    base = root.joinpath(*parts)
    for cand in (base.with_suffix(".py"), base / "__init__.py"):
        if cand.is_file():
            return cand
    return None


def parse(name: str, path: Path) -> ModuleCode:
    data = path.read_bytes()
    key = (name, hashlib.blake2b(data, digest_size=16).digest())
    if key not in _PARSED:
        try:
            tree = ast.parse(data, filename=str(path))
        except SyntaxError as err:
            raise ValueError(f"cannot hash the code of {path}: {err}") from err
        imports = imported_names(tree, name, path.name == "__init__.py")
        digest = hashlib.blake2b(ast.dump(strip_docstrings(tree)).encode(), digest_size=16).hexdigest()
        _PARSED[key] = ModuleCode(digest, tuple(dict.fromkeys(imports)))
    return _PARSED[key]


def closure(start: dict[str, Path], root: Path) -> dict[str, Path]:
    """Module name -> file of every project module reachable by imports from the `start` modules
    (name -> file; a start module need not lie under `root`, e.g. a test's stage)."""
    seen: dict[str, Path] = {}
    todo = list(start.items())
    while todo:
        name, path = todo.pop()
        if name in seen:
            continue
        seen[name] = path
        for dep in parse(name, path).imports:
            if dep not in seen:
                f = module_file(dep, root)
                if f is not None:
                    todo.append((dep, f))
    return seen


def code_hash(modules: list[str], root: Path, files: dict[str, Path] | None = None) -> str:
    """Hash of the code of `modules` and of every project module they import (transitively), plus the
    native sources of any of them listed in NATIVE_SOURCES. A module is found under `root`, else in
    `files` (name -> file)."""
    files = files or {}
    start = {}
    for name in modules:
        path = module_file(name, root) or files.get(name)
        if path is None:
            raise ValueError(f"module {name!r} is neither under {root} nor given a file")
        start[name] = Path(path)
    found = closure(start, root)
    h = hashlib.blake2b(digest_size=16)
    for name in sorted(found):
        h.update(f"{name}\0{parse(name, found[name]).digest}\n".encode())
        if name in NATIVE_SOURCES:
            folder, suffixes = NATIVE_SOURCES[name]
            for p in sorted((root / folder).rglob("*")):
                if p.is_file() and p.suffix in suffixes:
                    h.update(p.relative_to(root).as_posix().encode() + b"\0" + p.read_bytes())
    return h.hexdigest()
