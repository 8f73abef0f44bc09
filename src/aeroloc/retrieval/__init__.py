"""Stage 3: global descriptors and nearest-neighbour retrieval.

``models/`` (one file per VPR method, registry in ``models/__init__``), ``descriptors`` (batched description of
images), ``store`` (the resumable descriptor memmap), ``index`` (Faiss), ``database`` (a tile set + its
descriptor stores and indexes, ``build_global``), ``retriever`` (query -> top-N tiles).

Imports: aeroloc.maps and aeroloc.core.
"""
