import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))

import pytest

from campaign_fixture import campaign_args, write_config
from pipeline import cli


@pytest.fixture(scope="session")
def local_campaign(tmp_path_factory):
    """The tiny campaign run once on a local cluster: (data root, config file, stderr of the run)."""
    base = tmp_path_factory.mktemp("campaign_local")
    root, config = base / "data", write_config(base / "campaign.yaml")
    rc = cli.main(campaign_args(root, config))
    if rc != 0:
        raise RuntimeError(f"the local tiny campaign failed with exit code {rc}")
    return root, config
