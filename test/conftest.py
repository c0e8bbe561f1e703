"""Shared test fixtures: paths to the shared real data, skipping cleanly where it is absent."""

import os
from pathlib import Path

import pytest

# ROS 2 isolation for every test and subprocess: discovery stays on this machine, and each pytest
# run gets its own domain so parallel runs (or a user's live robot) never see our test traffic.
os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
os.environ.setdefault("ROS_DOMAIN_ID", str(1 + os.getpid() % 100))
os.environ.setdefault("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")

# The revisit model and bags, shared by node and CLI tests.
pytest_plugins = ["test.revisit_fixture", "test.reliability"]

REPO_ROOT = Path(__file__).resolve().parents[1]
# `shared/` sits beside the checkout (CI: a clean clone with ../shared next to it).
SHARED_DIR = REPO_ROOT.parent / "shared"


def require_shared(*relative: str) -> Path:
    """Path inside ../shared, or skip the calling test where it is absent (a user's fresh clone)."""
    path = SHARED_DIR.joinpath(*relative)
    if not path.exists():
        pytest.skip(f"shared data not available: {path}")
    return path


@pytest.fixture
def shared_dir() -> Path:
    return require_shared()


@pytest.fixture
def rtabmap_dir() -> Path:
    return require_shared("datasets", "rtabmap_samples")


@pytest.fixture
def kitti_dir() -> Path:
    return require_shared("datasets", "kitti00_first300")


@pytest.fixture
def golden_dir() -> Path:
    return require_shared("golden", "openfabmap_rtab")
