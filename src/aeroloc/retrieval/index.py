"""Faiss nearest-neighbour index over L2-normalised descriptors (inner product = cosine).

Any faiss factory string works: "Flat" (exact, default), "HNSW32", "IVF1024,PQ32" … Indexes that need training
are trained on the database descriptors; asking for more neighbours than there are tiles returns them all.

At scale (:func:`build_index_from_store`): ``auto`` picks the factory by size (:func:`choose_factory`: exact
under ``FLAT_MAX`` tiles, else PCA to 256-d + IVF with 8-bit scalar codes), trains it on a fixed sample and fills
it chunk by chunk from the memory-mapped store. IVF lists live in ``index.faiss.ivfdata`` (faiss
``OnDiskInvertedLists``, memory-mapped by faiss when read) and a flat index's vectors are memory-mapped too
(``IO_FLAG_MMAP_IFC``), so searching does not load the index into RAM. (faiss 1.15 crashes when an on-disk IVF
index is read with ``IO_FLAG_MMAP``; the on-disk lists are mapped without it.)
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
    """The index at ``path``, its vectors / inverted lists memory-mapped (see the module docstring)."""
    import faiss

    path = Path(path)
    if not path.is_file():
        raise AerolocError(f"{path}: index not found (rebuild with 'aeroloc build')")
    if _ivfdata(path).is_file():
        return faiss.read_index(str(path.resolve()))
    try:
        return faiss.read_index(str(path), faiss.IO_FLAG_MMAP_IFC)
    except RuntimeError:  # not a flat index: read it normally
        return faiss.read_index(str(path))


FLAT_MAX = 100_000  # exact search below this many tiles (16 KB/tile at 8192-d: 1.6 GB at the limit)
PCA_DIM = 256
TRAIN_MAX = 20_000  # training sample (8192-d float32: 655 MB at most)


def choose_factory(n: int, dim: int) -> str:
    """Exact ``Flat`` under ``FLAT_MAX`` tiles; above, ``PCA256,IVF{~4 sqrt(n)},SQ8`` (PCA only for larger
    descriptors). SQ8 keeps recall@10 near exact where PQ loses more (benchmarks/scale.py measures it)."""
    if n < FLAT_MAX:
        return "Flat"
    nlist = int(2 ** round(np.log2(4 * np.sqrt(n))))
    pre = f"PCA{PCA_DIM}," if dim > PCA_DIM else ""
    return f"{pre}IVF{nlist},SQ8"


def _ivfdata(path: Path) -> Path:
    return path.with_name(path.name + ".ivfdata")


def _sample_rows(npy: Path, n_pick: int) -> np.ndarray:
    """A fixed random sample of ``n_pick`` rows of the store as float32, read in sorted order."""
    mm = np.load(npy, mmap_mode="r")
    pick = np.sort(np.random.default_rng(0).choice(mm.shape[0], min(n_pick, mm.shape[0]), replace=False))
    return np.ascontiguousarray(mm[pick], dtype=np.float32)


def _train(index, npy: Path, n: int) -> None:
    """Train on a fixed sample of at most ``TRAIN_MAX`` rows (a PCA chain trains its transform, then the IVF)."""
    if n < 40:
        raise AerolocError(f"faiss index needs training data; {n} descriptors is too few (use Flat)")
    _skip_polysemous_training(index)
    x = _sample_rows(npy, TRAIN_MAX)
    try:
        index.train(x)
    except RuntimeError as exc:
        raise AerolocError(f"faiss index training failed on {len(x)} descriptors: {str(exc).splitlines()[0]}") from None
    del x


def build_index_from_store(npy, path, factory: str = "auto", nprobe: int = 32, chunk: int = 4096) -> str:
    """Build the index of the ``.npy`` store ``npy`` into ``path`` chunk by chunk; returns the factory used."""
    import faiss

    from aeroloc.retrieval.shards import iter_rows

    npy, path = Path(npy), Path(path)
    n, d = np.load(npy, mmap_mode="r").shape
    factory = choose_factory(n, d) if factory == "auto" else factory
    try:
        index = faiss.index_factory(d, factory, faiss.METRIC_INNER_PRODUCT)
    except RuntimeError as exc:
        raise AerolocError(f"faiss index '{factory}' cannot be built for dim {d}: {str(exc).splitlines()[0]}") from None
    if not index.is_trained:
        _train(index, npy, n)
    ivf = _ivf_or_none(index)
    _ivfdata(path).unlink(missing_ok=True)
    if ivf is not None:
        lists = faiss.OnDiskInvertedLists(ivf.nlist, ivf.code_size, str(_ivfdata(path).resolve()))
        ivf.replace_invlists(lists, True)
        lists.this.disown()  # the index owns the lists now (else Python frees them under it)
        ivf.nprobe = nprobe
    for rows in iter_rows(npy, chunk):
        index.add(np.ascontiguousarray(rows, dtype=np.float32))
    save_index(index, path)
    return factory


def _ivf_or_none(index):
    import faiss

    try:
        return faiss.extract_index_ivf(index)
    except RuntimeError:
        return None
