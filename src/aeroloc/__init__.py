"""aeroloc: GNSS-free localization of aerial images against georeferenced maps.

The whole Python API on one page (imported on first use, so ``import aeroloc`` stays cheap)::

    from aeroloc import LocalizeOptions, Localizer, build_database, read_image

    db = build_database("map.tif", "db/", tile_m=1000)        # tiles + descriptors + local features
    localizer = Localizer(db, LocalizeOptions(north_up=True))
    fix = localizer("photo.jpg", read_image("photo.jpg"))
    print(fix.lat, fix.lon, fix.status)                      # NaN, NaN, "not localized: ..." when unsure

Stages, in the order a query meets them: maps (:class:`Map`, :func:`open_map`, :class:`TileGrid`, :class:`Tile`),
retrieval (:class:`Database`, :data:`METHODS`), matching (:data:`RERANKERS`), localization (:class:`Localizer`,
:class:`LocalizeOptions`, :class:`Localization`, :func:`localize_queries`), evaluation (:func:`evaluate`).
Coordinates in the public API are always ``(lat, lon)`` in WGS84 degrees; readers of formats that put the
longitude first convert at the border.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

__version__ = "0.1.0"

_EXPORTS = {
    "AerolocError": "aeroloc.core.errors",
    "read_image": "aeroloc.core.images",
    "Query": "aeroloc.core.queries",
    "load_queries": "aeroloc.core.queries",
    "Map": "aeroloc.maps.sources",
    "open_map": "aeroloc.maps.sources",
    "Tile": "aeroloc.maps.tiling",
    "TileGrid": "aeroloc.maps.tiling",
    "write_tiles": "aeroloc.maps.tiling",
    "Database": "aeroloc.retrieval.database",
    "build_global": "aeroloc.retrieval.database",
    "METHODS": "aeroloc.retrieval.models",
    "RERANKERS": "aeroloc.matching.registry",
    "build_local": "aeroloc.matching.features",
    "build_database": "aeroloc.localization.build",
    "LocalizeOptions": "aeroloc.localization.options",
    "Localizer": "aeroloc.localization.localizer",
    "Localization": "aeroloc.localization.results",
    "read_localizations": "aeroloc.localization.results",
    "localize_queries": "aeroloc.localization.run",
    "evaluate": "aeroloc.bench.metrics",
}
__all__ = [
    "METHODS",
    "RERANKERS",
    "AerolocError",
    "Database",
    "Localization",
    "LocalizeOptions",
    "Localizer",
    "Map",
    "Query",
    "Tile",
    "TileGrid",
    "__version__",
    "build_database",
    "build_global",
    "build_local",
    "evaluate",
    "load_queries",
    "localize_queries",
    "open_map",
    "read_image",
    "read_localizations",
    "write_tiles",
]

if TYPE_CHECKING:
    from aeroloc.bench.metrics import evaluate
    from aeroloc.core.errors import AerolocError
    from aeroloc.core.images import read_image
    from aeroloc.core.queries import Query, load_queries
    from aeroloc.localization.build import build_database
    from aeroloc.localization.localizer import Localizer
    from aeroloc.localization.options import LocalizeOptions
    from aeroloc.localization.results import Localization, read_localizations
    from aeroloc.localization.run import localize_queries
    from aeroloc.maps.sources import Map, open_map
    from aeroloc.maps.tiling import Tile, TileGrid, write_tiles
    from aeroloc.matching.features import build_local
    from aeroloc.matching.registry import RERANKERS
    from aeroloc.retrieval.database import Database, build_global
    from aeroloc.retrieval.models import METHODS


def __getattr__(name: str):
    if name in _EXPORTS:
        value = getattr(importlib.import_module(_EXPORTS[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'aeroloc' has no attribute {name!r}")


def __dir__():
    return sorted(__all__)
