"""Shared fixtures: the real data in ../shared/data (read in place, never copied into the repo)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("AEROLOC_DATA", REPO.parent / "shared" / "data"))


@pytest.fixture(scope="session", autouse=True)
def private_cache(tmp_path_factory):
    """The suite's own $AEROLOC_CACHE (map hashes, downloaded weights): tests never write into the user's
    ~/.cache/aeroloc, and a hash cached there by another checkout can't make a test pass."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("AEROLOC_CACHE", str(tmp_path_factory.mktemp("aeroloc-cache")))
        yield


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


# The pipeline tests' database: the NAIP map at zoom 1 (256 px = 1.28 km tiles), overlap 0.5 -> 35 tiles. At overlap 0
# (12 tiles) most queries straddle tile borders and XFeat-VLAD retrieval is no better than chance (measured R@5 0.62
# vs ~0.5 random); at overlap 0.5 it reaches R@1 0.42, R@5 0.78 on naip-nd/dev.
NAIP_DB_ZOOM, NAIP_DB_OVERLAP = 1.0, 0.5


@pytest.fixture(scope="session")
def naip_tiles_db(naip_map, tmp_path_factory) -> Path:
    """Tiles only (tiles.csv, tiles.json, images/) of the pipeline tests' NAIP database."""
    from aeroloc.maps.tiling import write_tiles

    folder = tmp_path_factory.mktemp("naip-db")
    write_tiles(naip_map, folder, NAIP_DB_ZOOM, NAIP_DB_OVERLAP, progress=False)
    return folder


@pytest.fixture(scope="session")
def naip_db_build(naip_tiles_db, naip_map):
    """The same folder after one ``aeroloc build`` (xfeat-vlad + xfeat-lighterglue features), and its output."""
    import contextlib
    import io
    import types

    from aeroloc.cli import main

    out = io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(io.StringIO()):
        code = main(
            [
                "build",
                str(naip_map),
                "--zoom",
                str(NAIP_DB_ZOOM),
                "--overlap",
                str(NAIP_DB_OVERLAP),
                "--out",
                str(naip_tiles_db),
                "--method",
                "xfeat-vlad",
                "--local",
                "xfeat-lighterglue",
                "--device",
                "cpu",
            ]
        )
    assert code == 0, out.getvalue()
    return types.SimpleNamespace(folder=naip_tiles_db, stdout=out.getvalue())


@pytest.fixture(scope="session")
def naip_db(naip_db_build) -> Path:
    return naip_db_build.folder


def pytest_configure(config):
    """Tests run two processes on two cores (pytest -n 2): one torch thread each avoids oversubscription."""
    try:
        import torch

        torch.set_num_threads(1)
    except ImportError:
        pass
