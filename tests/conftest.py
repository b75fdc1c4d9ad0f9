"""Tests marked `cuda` run only where torch sees a GPU (`pytest -m cuda` on a GPU machine) and are skipped
elsewhere, with the reason shown."""
import pytest
import torch


def pytest_collection_modifyitems(config, items):
    if torch.cuda.is_available():
        return
    skip = pytest.mark.skip(reason="needs a CUDA device")
    for item in items:
        if item.get_closest_marker("cuda") is not None:
            item.add_marker(skip)
