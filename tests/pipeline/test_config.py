from dataclasses import dataclass, field
from typing import Literal

import pytest

from pipeline import config as cfgmod


@dataclass(frozen=True)
class Inner:
    n_levels: int = 8
    """levels of the grid."""


@dataclass(frozen=True)
class Section:
    seed: int = 0
    """random seed."""
    rate: float = 0.5
    mode: Literal["a", "b"] = "a"
    flag: bool = False
    names: tuple[str, ...] = ()
    inner: Inner = field(default_factory=Inner)


SECTIONS = {"s": Section}


def test_set_overrides_are_coerced_to_declared_types():
    raw = cfgmod.parse_set(["s.seed=3", "s.rate=1e-3", "s.mode=b", "s.flag=true", "s.names=x,y",
                            "s.inner.n_levels=12"])
    cfg = cfgmod.resolve(SECTIONS, raw)["s"]
    assert cfg == Section(seed=3, rate=1e-3, mode="b", flag=True, names=("x", "y"), inner=Inner(12))


@pytest.mark.parametrize("item, message", [
    ("s.sed=3", "unknown key(s) ['sed']; valid keys: ['seed'"),
    ("x.seed=3", "unknown config section(s) ['x']"),
    ("s.seed=1.5", "expected an integer"),
    ("s.mode=c", "is not one of ['a', 'b']"),
    ("s.flag=maybe", "expected true/false"),
    ("seed=3", "key must be section.key"),
    ("s.seed", "expected section.key=value"),
])
def test_bad_overrides_name_what_exists(item, message):
    with pytest.raises(cfgmod.ConfigError, match=None) as err:
        cfgmod.resolve(SECTIONS, cfgmod.parse_set([item]))
    assert message in str(err.value)


def test_file_then_set_precedence(tmp_path):
    f = tmp_path / "c.yaml"
    f.write_text("s:\n  seed: 7\n  rate: 0.25\n")
    raw = cfgmod.merge(cfgmod.load_file(f), cfgmod.parse_set(["s.seed=9"]))
    cfg = cfgmod.resolve(SECTIONS, raw)["s"]
    assert (cfg.seed, cfg.rate) == (9, 0.25)


def test_bad_yaml_file_is_a_clear_error(tmp_path):
    f = tmp_path / "c.yaml"
    f.write_text("s: [unclosed\n")
    with pytest.raises(cfgmod.ConfigError, match="not valid YAML"):
        cfgmod.load_file(f)


def test_field_docs_are_read_from_source():
    docs = cfgmod.field_docs(Section)
    assert docs["seed"] == "random seed."
    lines = cfgmod.describe("s", Section)
    assert "s.inner.n_levels = 8    # levels of the grid." in lines
