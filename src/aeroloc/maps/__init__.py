"""Stage 1-2: the map and its tiles.

``sources`` (a georeferenced raster: GeoTIFF, seed tile folder, XYZ folder -> :class:`~aeroloc.maps.sources.Map`
with pixel windows), ``tiling`` (:class:`~aeroloc.maps.tiling.TileGrid` at any zoom/overlap, exact corner
georeference, ``tiles.csv``), and map acquisition: ``download`` + ``providers`` (XYZ / Google Static tiles),
``orthophoto`` (``aeroloc import``: a COG with overviews).

Imports: aeroloc.core only.
"""
