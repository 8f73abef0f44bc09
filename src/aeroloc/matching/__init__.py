"""Stage 4 building blocks: local features, matchers, geometric verification, dense structural matching.

``models/`` (extractors and matchers, one file per method), ``registry`` (the one table of re-rankers: extractor
+ matcher + cascade settings, one default), ``features`` (extraction at a working resolution and rotation, the
per-database feature store ``build_local``), ``store`` (HDF5 feature store), ``verify`` (RANSAC homography /
similarity), ``dense`` (CFOG descriptors and FFT correlation).

Imports: aeroloc.retrieval (SelaVPR's local features come from its global model), aeroloc.maps, aeroloc.core.
"""
