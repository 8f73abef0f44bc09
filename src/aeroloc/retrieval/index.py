"""Faiss nearest-neighbour index over L2-normalised descriptors (inner product = cosine).

Any faiss factory string works: "Flat" (exact, default), "HNSW32", "IVF1024,PQ32" … Indexes that need training
are trained on the database descriptors; asking for more neighbours than there are tiles returns them all.

At scale (:func:`build_index_from_store`): ``auto`` picks the factory by size (:func:`choose_factory`: exact
under ``FLAT_MAX`` tiles, else HNSW over 8-bit scalar codes; PCA + IVF on request), trains it on a fixed sample and fills
it chunk by chunk from the memory-mapped store. IVF lists live in ``index.faiss.ivfdata`` (faiss
``OnDiskInvertedLists``, memory-mapped by faiss when read) and a flat index's vectors are memory-mapped too
(``IO_FLAG_MMAP_IFC``), so searching does not load the index into RAM. (faiss 1.15 crashes when an on-disk IVF
index is read with ``IO_FLAG_MMAP``; the on-disk lists are mapped without it.)
"""

from __future__ import annotations

import contextlib
import struct
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
TRAIN_MAX = 20_000  # training sample of an index without PCA (8192-d float32: 655 MB at most)
# HNSW search breadth: on real 8192-d effnet-vlad tiles HNSW32,SQ8 keeps recall@10 0.986-0.993 of exact at 256,
# 0.94-0.99 at 64 (benchmarks/scale.py); faiss's default 16 loses more
EF_SEARCH = 256
PCA_TRAIN_MAX = 4_000  # rows the PCA is fitted on (4000 x 8192 float32: 131 MB)


def choose_factory(n: int, dim: int) -> str:
    """Exact ``Flat`` under ``FLAT_MAX`` tiles; above, ``HNSW32,SQ8``: the one approximate index that keeps
    recall@10 >= 0.98 of exact on real tiles (0.986-0.995 on NAIP, levir-tx and szada-hu, benchmarks/scale.py).
    PCA + IVF (256 or 1024 dims) kept only 0.19-0.58 of the exact top-10 for real photos: 256 components hold 29 %
    of these 8192-d descriptors' variance. HNSW lives in RAM (~8.4 KB/tile at 8192-d + SQ8): a country needs
    a smaller descriptor or ``--index PCA256,IVF4096,SQ8`` (on disk, 1.8 GB at 10^6) and its lower recall."""
    if n < FLAT_MAX:
        return "Flat"
    return "HNSW32,SQ8"


def _ivfdata(path: Path) -> Path:
    return path.with_name(path.name + ".ivfdata")


def _sample_rows(npy: Path, n_pick: int) -> np.ndarray:
    """A fixed random sample of ``n_pick`` rows of the store as float32, read in sorted order."""
    mm = np.load(npy, mmap_mode="r")
    pick = np.sort(np.random.default_rng(0).choice(mm.shape[0], min(n_pick, mm.shape[0]), replace=False))
    return np.ascontiguousarray(mm[pick], dtype=np.float32)


def _train(index, npy: Path, n: int) -> None:
    """Train on fixed samples of the store. A ``PCA…`` chain fits its transform on at most ``PCA_TRAIN_MAX``
    rows with a randomized SVD (:func:`fit_pca`: faiss's own PCA on 8192-d descriptors took > 10 min) and the
    index after it on at most ``TRAIN_MAX`` rows already reduced; other indexes train on ``TRAIN_MAX`` rows."""
    import faiss

    if n < 40:
        raise AerolocError(f"faiss index needs training data; {n} descriptors is too few (use Flat)")
    _skip_polysemous_training(index)
    pca = _pca_or_none(index)
    if pca is None:
        _train_on(index, _sample_rows(npy, TRAIN_MAX))
        return
    fit_pca(pca, _sample_rows(npy, PCA_TRAIN_MAX))
    sub = faiss.downcast_index(index).index
    _train_on(sub, _reduced_sample(pca, npy, TRAIN_MAX))
    index.is_trained = True


def _train_on(index, x: np.ndarray) -> None:
    """``index.train(x)`` with faiss's errors (too few points for the lists …) as one-line AerolocErrors."""
    try:
        index.train(x)
    except RuntimeError as exc:
        raise AerolocError(f"faiss index training failed on {len(x)} descriptors: {str(exc).splitlines()[0]}") from None


def _pca_or_none(index):
    """The PCA of a ``PCA…,<index>`` factory (a pre-transform chain of exactly one PCA), else None."""
    import faiss

    index = faiss.downcast_index(index)
    if not isinstance(index, faiss.IndexPreTransform) or index.chain.size() != 1:
        return None
    vt = faiss.downcast_VectorTransform(index.chain.at(0))
    return vt if isinstance(vt, faiss.PCAMatrix) else None


def _reduced_sample(pca, npy: Path, n_pick: int, chunk: int = 2048) -> np.ndarray:
    """The fixed training sample of ``n_pick`` rows, PCA-reduced chunk by chunk (never all of it at full dim)."""
    mm = np.load(npy, mmap_mode="r")
    pick = np.sort(np.random.default_rng(0).choice(mm.shape[0], min(n_pick, mm.shape[0]), replace=False))
    parts = [
        pca.apply(np.ascontiguousarray(mm[pick[s : s + chunk]], dtype=np.float32)) for s in range(0, len(pick), chunk)
    ]
    return np.ascontiguousarray(np.concatenate(parts), dtype=np.float32)


def fit_pca(pca, x: np.ndarray, iters: int = 2, oversample: int = 64) -> None:
    """Fit faiss ``PCAMatrix`` ``pca`` on the rows ``x`` with a randomized SVD (Halko et al.: a random range of
    ``d_out + oversample`` columns refined by ``iters`` power iterations, fixed seed): seconds on 4000 x 8192
    where faiss's eigendecomposition of the 8192 x 8192 covariance takes many minutes; the leading components
    are the same to < 1 % in variance. Sets the mean, components and variances, then faiss's own ``A``, ``b``."""
    import faiss

    n, d = x.shape
    k = pca.d_out
    if n < k:
        raise AerolocError(f"PCA to {k}-d needs at least {k} training descriptors, got {n}")
    mean = x.mean(0, dtype=np.float64).astype(np.float32)
    c = x - mean
    width = min(k + oversample, n, d)
    q, _ = np.linalg.qr(c.T @ np.random.default_rng(0).standard_normal((n, width)).astype(np.float32))
    for _ in range(iters):
        z, _ = np.linalg.qr(c @ q)
        q, _ = np.linalg.qr(c.T @ z)
    _, sv, vt = np.linalg.svd(c @ q, full_matrices=False)
    comps = np.ascontiguousarray((vt @ q.T)[:k], dtype=np.float32)
    faiss.copy_array_to_vector(mean, pca.mean)
    faiss.copy_array_to_vector((sv[:k] ** 2 / max(n - 1, 1)).astype(np.float32), pca.eigenvalues)
    faiss.copy_array_to_vector(comps.ravel(), pca.PCAMat)
    pca.is_trained = True
    pca.prepare_Ab()


def build_index_from_store(
    npy, path, factory: str = "auto", nprobe: int = 32, chunk: int = 4096, ef_search: int = EF_SEARCH
) -> str:
    """Build the index of the ``.npy`` store ``npy`` into ``path`` chunk by chunk; returns the factory used.
    ``nprobe`` (IVF) and ``ef_search`` (HNSW) are saved with the index, so a search uses them.

    ``Flat`` is streamed to the file (:func:`_write_flat`) rather than filled in RAM: the exact index of 10^5
    8192-d tiles is 3.3 GB of float32, and holding it made the build's peak RSS grow with the map."""
    import faiss

    from aeroloc.retrieval.shards import iter_rows

    npy, path = Path(npy), Path(path)
    n, d = np.load(npy, mmap_mode="r").shape
    factory = choose_factory(n, d) if factory == "auto" else factory
    try:
        index = faiss.index_factory(d, factory, faiss.METRIC_INNER_PRODUCT)
    except RuntimeError as exc:
        raise AerolocError(f"faiss index '{factory}' cannot be built for dim {d}: {str(exc).splitlines()[0]}") from None
    _ivfdata(path).unlink(missing_ok=True)
    flat = faiss.downcast_index(index)
    if type(flat) in (faiss.IndexFlat, faiss.IndexFlatIP) and flat.metric_type == faiss.METRIC_INNER_PRODUCT:
        _write_flat(npy, path, n, d, chunk)
        return factory
    if not index.is_trained:
        _train(index, npy, n)
    ivf = _ivf_or_none(index)
    if ivf is not None:
        lists = faiss.OnDiskInvertedLists(ivf.nlist, ivf.code_size, str(_ivfdata(path).resolve()))
        ivf.replace_invlists(lists, True)
        lists.this.disown()  # the index owns the lists now (else Python frees them under it)
        ivf.nprobe = nprobe
    hnsw = getattr(faiss.downcast_index(index), "hnsw", None)
    if hnsw is not None:
        hnsw.efSearch = ef_search
    for rows in iter_rows(npy, chunk):
        index.add(np.ascontiguousarray(rows, dtype=np.float32))
    save_index(index, path)
    return factory


def _write_flat(npy: Path, path: Path, n: int, d: int, chunk: int) -> None:
    """Write an exact inner-product index of the store's rows in faiss's own file format (the same bytes as
    ``faiss.write_index`` of an ``IndexFlatIP`` filled with them; a test compares), chunk by chunk, so RAM holds
    one chunk, not the index. Written to ``.part`` and renamed, so a full disk leaves no half index."""
    from aeroloc.retrieval.shards import iter_rows

    # fourcc, d (int32), ntotal, two unused idx_t (1 << 20), is_trained (bool), metric (int32: 0 = inner
    # product), then the vectors as a size_t count of floats and the floats
    header = b"IxFI" + struct.pack("<iqqq?iQ", d, n, 1 << 20, 1 << 20, True, 0, n * d)
    tmp = path.with_name(path.name + ".part")
    with open(tmp, "wb") as f:
        f.write(header)
        for rows in iter_rows(npy, chunk):
            f.write(np.ascontiguousarray(rows, dtype="<f4").tobytes())
    tmp.replace(path)


def _ivf_or_none(index):
    import faiss

    try:
        return faiss.extract_index_ivf(index)
    except RuntimeError:
        return None
