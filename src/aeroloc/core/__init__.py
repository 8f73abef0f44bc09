"""The ground floor: what every stage needs and nothing stage-specific.

``errors`` (the one user-facing exception), ``geo`` (CRS, Web Mercator, geodesics), ``images`` (read/write,
no-data masks), ``frames`` (resizing and rotating images, mapping points between frames), ``io`` (atomic files,
cache keys, resumable CSV), ``device`` (CPU/GPU choice, BLAS threads), ``weights`` (finding model checkpoints),
``registry`` (lazy name -> class tables), ``queries`` (query sets and their truth), ``priors`` (per-query
ground resolution and heading, each optional, with tolerances).

Imports go down only: core imports nothing else from aeroloc.
"""
