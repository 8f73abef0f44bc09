"""Shared fixtures: the real data in ../shared/data (read in place, never copied into the repo)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("AEROLOC_DATA", REPO.parent / "shared" / "data"))


@pytest.fixture(scope="session")
def data_dir() -> Path:
    if not DATA.is_dir():
        pytest.skip(f"real data not found at {DATA} (set AEROLOC_DATA)")
    return DATA


@pytest.fixture(scope="session")
def naip_map(data_dir) -> Path:
    return data_dir / "naip-nd" / "map_20200831.tif"


@pytest.fixture(scope="session")
def naip_dev(data_dir) -> Path:
    return data_dir / "naip-nd" / "dev" / "queries.csv"


@pytest.fixture(scope="session")
def toledo_map(data_dir) -> Path:
    return data_dir / "toledo" / "orthomosaic.tif"


@pytest.fixture(scope="session")
def toledo_queries(data_dir) -> Path:
    return data_dir / "toledo" / "queries.csv"


def pytest_configure(config):
    """Tests run two processes on two cores (pytest -n 2): one torch thread each avoids oversubscription."""
    try:
        import torch

        torch.set_num_threads(1)
    except ImportError:
        pass
