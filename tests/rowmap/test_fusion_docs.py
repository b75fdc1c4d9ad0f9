"""docs/fusion.md against the code it documents: its cost table names every term with its weight, its settings
table every setting with its default, and every test it cites exists (so neither drifts from the code)."""
from __future__ import annotations

import ast
import dataclasses
import re
from pathlib import Path

from rowmap.fusion import TERMS, Config
from rowmap.fusion.assignment import WEIGHTS

ROOT = Path(__file__).resolve().parents[2]


def table(section: str) -> list[list[str]]:
    """The body rows of the first table under `## <section>` in docs/fusion.md, as lists of cells."""
    text = (ROOT / "docs" / "fusion.md").read_text().split(f"\n## {section}\n", 1)[1].split("\n## ", 1)[0]
    rows = [line for line in text.splitlines() if line.startswith("|")]
    return [[c.strip() for c in r.strip("|").split("|")] for r in rows[2:]]


def test_the_cost_table_lists_every_term_with_its_weight_and_cites_settings_and_tests_that_exist():
    rows = table("The cost")
    assert [re.match(r"(\w+) \(([\d.]+)\)", r[0]).groups() for r in rows] == [(t, str(WEIGHTS[t])) for t in TERMS]
    fields = {f.name for f in dataclasses.fields(Config)}
    tree = ast.parse((ROOT / "tests" / "rowmap" / "test_fusion.py").read_text())
    tests = [n.name for n in tree.body if isinstance(n, ast.FunctionDef) and n.name.startswith("test_")]
    for term, *_, settings, cited in rows:
        assert set(re.findall(r"`(\w+)`", settings)) <= fields, term
        names = re.findall(r"`([\w.]+)`", cited)
        assert names, term
        for name in names:    # '..._every_term_off...' cites the test whose name holds 'every_term_off'
            assert any(name.strip("._") in t for t in tests), (term, name)


def test_the_settings_table_lists_every_setting_in_order_with_its_default():
    rows = table("Settings")
    fields = dataclasses.fields(Config)
    assert [r[0].strip("`") for r in rows] == [f.name for f in fields]
    for (_, what), f in zip(rows, fields):
        default = re.search(r"\(([^()]*)\)$", what).group(1)
        expected = "none" if f.default == () else str(f.default)
        expected = expected.lower() if isinstance(f.default, bool) else expected
        assert default == expected, f.name
