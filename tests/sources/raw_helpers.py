"""Helpers for the source tests (kept out of conftest.py so tests can import them)."""
import shutil
from pathlib import Path

import pytest

FIXTURES = Path(__file__).resolve().parents[2].parent / "shared" / "fixtures"


def shared_fixture(rel: str) -> Path:
    p = FIXTURES / rel
    if not p.exists():
        pytest.skip(f"shared fixture {p} not present (the shared/ folder beside the repository)")
    return p


def copy_raw(src: Path, dst_root: Path, drop_png_layout: bool = False) -> Path:
    """A copy of the raw folder (optionally with only the bag and the detector output)."""
    dst = dst_root / "raw" / "t"
    shutil.copytree(src, dst)
    if drop_png_layout:
        shutil.rmtree(dst / "rgb")
        shutil.rmtree(dst / "depth")
    return dst
