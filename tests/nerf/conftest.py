"""Fixtures shared by the model tests: one tiny ray-cast window (with its ground-truth labels) and one short
colour fit of it, made once per test session. Tests read them and never change them: a test that needs to
change a model fits its own."""
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))
from nerf.config import preset  # noqa: E402


@pytest.fixture(scope="session")
def labelled_window():
    """(WindowData of 6 frames 40 x 24, odd ones train; semantic [6, 24, 40]; instance [6, 24, 40])."""
    from scene_fixture import tiny_window  # the synthetic scene needs Open3D: only the tests that use it import it

    return tiny_window(n=6, w=40, h=24, labels=True)


@pytest.fixture(scope="session")
def window(labelled_window):
    return labelled_window[0]


@pytest.fixture(scope="session")
def short_fit(window):
    """FitResult of `window` with SHORT_FIT (validation frames rendered)."""
    from scene_fixture import SHORT_FIT

    from nerf.trainer import fit_window

    return fit_window(window, preset("cpu", **SHORT_FIT))
