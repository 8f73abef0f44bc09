"""Everything a :class:`~aeroloc.localization.localizer.Localizer` needs, built (or found cached) in one call:
tiles, global descriptors + index, the ground the map shows twice (aeroloc.retrieval.echoes) and the re-ranker's
tile features."""

from __future__ import annotations

from aeroloc.matching.registry import DEFAULT_RERANKER
from aeroloc.retrieval.models import DEFAULT_METHOD


def build_database(
    map_path,
    out_dir,
    zoom: float = 1.0,
    overlap: float = 0.5,
    tile_m: float | None = None,
    method: str = DEFAULT_METHOD,
    rerank: str | None = DEFAULT_RERANKER,
    device="auto",
    progress: bool = False,
    ray: str | None = None,
    write_images: bool = False,
    local_turns: bool = False,
    global_turns: bool = False,
):
    """The database of ``map_path`` (GeoTIFF, tile folder or XYZ folder) in ``out_dir``: tiles at ``zoom`` /
    ``overlap`` (or ``tile_m`` metres a side), ``method`` descriptors, ``rerank`` features. Every part is cached
    and resumable per shard, so calling it again costs only the checks; ``ray`` (an address, or ``"local"``)
    builds the shards on a Ray cluster with the same result. Tiles stay windows of the map unless
    ``write_images``; ``local_turns``: the re-ranker's tile features at eight turns too (photos of unknown heading
    extracted once; x8 their disk and build time); ``global_turns``: the tiles' descriptors at eight turns too
    (a photo of unknown heading retrieved with one descriptor; x8 descriptors and index). Returns the opened
    :class:`~aeroloc.retrieval.database.Database`."""
    from aeroloc.core.device import pick_device
    from aeroloc.maps.tiling import write_tiles
    from aeroloc.matching.features import build_local
    from aeroloc.retrieval.database import Database, build_global

    device = pick_device(device)
    write_tiles(map_path, out_dir, zoom, overlap, tile_m, progress=progress, write_images=write_images)
    db = Database(out_dir)
    build_global(db, method, device=device, progress=progress, ray=ray, turns=global_turns)
    if rerank:
        from aeroloc.retrieval.echoes import build_echoes

        build_echoes(db, method)  # ground the map shows twice: fixes there are checked at both places
        build_local(db, rerank, device, progress=progress, ray=ray, turns=local_turns)
    return db
