"""Faiss nearest-neighbour index over L2-normalised descriptors (inner product = cosine).

Any faiss factory string works: "Flat" (exact, default), "HNSW32", "IVF1024,PQ32" … Indexes that need training
are trained on the database descriptors; asking for more neighbours than there are tiles returns them all.
"""

from __future__ import annotations

import contextlib
from pathlib import Path

import numpy as np

from aeroloc.core.errors import AerolocError


def build_index(descriptors: np.ndarray, factory: str = "Flat"):
    import faiss

    x = np.ascontiguousarray(descriptors, dtype=np.float32)
    n, d = x.shape
    try:
        index = faiss.index_factory(d, factory, faiss.METRIC_INNER_PRODUCT)
    except RuntimeError as exc:
        raise AerolocError(f"faiss index '{factory}' cannot be built for dim {d}: {str(exc).splitlines()[0]}") from None
    if not index.is_trained:
        _skip_polysemous_training(index)
        if n < 40:
            raise AerolocError(f"faiss index '{factory}' needs training data; {n} descriptors is too few (use Flat)")
        try:
            index.train(x)
        except RuntimeError as exc:
            raise AerolocError(
                f"faiss index '{factory}' training failed on {n} descriptors: {str(exc).splitlines()[0]}"
            ) from None
    index.add(x)
    return index


def _skip_polysemous_training(index) -> None:
    """PQ indexes from the factory train polysemous codes by default: ~35 s extra on a small IVF16,PQ8 and only
    of use for polysemous (Hamming) search, which aeroloc never turns on."""
    import faiss

    parts = [index]
    with contextlib.suppress(RuntimeError):  # not an IVF index
        parts.append(faiss.extract_index_ivf(index))
    storage = getattr(faiss.downcast_index(index), "storage", None)  # HNSW32,PQ8 …
    if storage is not None:
        parts.append(storage)
    for part in parts:
        part = faiss.downcast_index(part)
        if hasattr(part, "do_polysemous_training"):
            part.do_polysemous_training = False


def search(index, queries: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """(scores, ids) of the k best tiles per query, best first; k is capped at the number of tiles."""
    if k < 1:
        raise AerolocError(f"top-N must be >= 1, got {k}")
    k = min(k, index.ntotal)
    q = np.ascontiguousarray(np.atleast_2d(queries), dtype=np.float32)
    scores, ids = index.search(q, k)
    return scores, ids


def save_index(index, path) -> None:
    import faiss

    path = Path(path)
    tmp = path.with_name(path.name + ".part")
    faiss.write_index(index, str(tmp))
    tmp.replace(path)


def load_index(path):
    import faiss

    path = Path(path)
    if not path.is_file():
        raise AerolocError(f"{path}: index not found (rebuild with 'aeroloc build')")
    return faiss.read_index(str(path))
