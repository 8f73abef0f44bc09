"""Faiss nearest-neighbour index over L2-normalised descriptors (inner product = cosine).

Any faiss factory string works: "Flat" (exact, default), "HNSW32", "IVF1024,PQ32" … Indexes that need training
are trained on the database descriptors; asking for more neighbours than there are tiles returns them all.

At scale (:func:`build_index_from_store`): ``auto`` picks the factory by size (:func:`choose_factory`: exact
under ``FLAT_MAX`` tiles, else a two-stage index), trains it on a fixed sample and fills it chunk by chunk from
the memory-mapped store. A factory ending in ``,Rerank<R>`` is two-stage (:class:`RerankIndex`): the faiss index
before it is a compact coarse index (``PCA1024,L2norm,HNSW32,SQ8``: 8192-d descriptors reduced to 1024 and
normalised, 8-bit codes in an HNSW graph, ~1.3 KB/tile) whose ``R`` best candidates are scored exactly against
the float16 store on disk (read with ``pread``, never mapped or loaded), so RAM holds the coarse index only and
the ranking of the top is that of exact search. IVF lists live in ``index.faiss.ivfdata`` (faiss
``OnDiskInvertedLists``, memory-mapped by faiss when read) and a flat index's vectors are memory-mapped too
(``IO_FLAG_MMAP_IFC``), so searching does not load the index into RAM. (faiss 1.15 crashes when an on-disk IVF
index is read with ``IO_FLAG_MMAP``; the on-disk lists are mapped without it.)
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import struct
from pathlib import Path

import numpy as np

from aeroloc.core.errors import AerolocError
from aeroloc.core.io import atomic_write_text
from aeroloc.retrieval.hugepages import collapse_index


def build_index(descriptors: np.ndarray, factory: str = "Flat"):
    x = np.ascontiguousarray(descriptors, dtype=np.float32)
    n, d = x.shape
    index = make_index(d, factory)
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


_PREFIX = re.compile(r"^(?P<outer>PCA(?P<pca>\d+)(?:,L2norm)?),Prefix(?P<p>\d+),(?P<graph>.+),Refine(?P<kf>\d+)$")


def make_index(d: int, factory: str):
    """An empty inner-product faiss index of ``factory`` (any faiss factory string, or aeroloc's prefix form
    below), faiss's errors as one-line AerolocErrors.

    ``PCA<D>[,L2norm],Prefix<P>,<graph>,Refine<F>`` is a coarse index in two steps behind one PCA: the graph
    (e.g. ``HNSW32,SQ8``) holds only the first ``P`` of the ``D`` components (the ones of most variance,
    renormalised), so its walk computes distances ~D/P times cheaper; its ``F`` x k best are re-scored with
    8-bit codes of all ``D`` components (faiss ``IndexRefine``), which restores the ranking of the full
    projection. The walk was the largest cost of a two-stage query at 10^6 tiles (4.3 of 9.0 ms at 1024-d).
    Not ``auto``'s: on NAIP's cross-season photos the leading components miss their neighbours (recall@10 of
    exact 0.86-0.88 with a 256-component graph, even re-scoring 16 x 150 of its best; 0.90-0.92 with 512,
    against 0.985 for ``auto``; benchmarks/scale.py --factories three-stage), though on levir-tx and szada-hu
    it keeps >= 0.99. At 10^6 tiles it costs 0.66x ``auto``'s CPU per query (14.5 vs 22.1 ms on one machine): a
    faster choice where recall matters less."""
    import faiss

    m = _PREFIX.match(factory)
    try:
        if m is None:
            return faiss.index_factory(d, factory, faiss.METRIC_INNER_PRODUCT)
        D, P, kf = int(m["pca"]), int(m["p"]), int(m["kf"])
        if not 0 < P < D or kf < 1:
            raise AerolocError(f"'{factory}': the prefix must be shorter than the PCA (0 < P < {D}) and Refine >= 1")
        graph = faiss.index_factory(P, m["graph"], faiss.METRIC_INNER_PRODUCT)
        prefix = faiss.IndexPreTransform(graph)
        prefix.prepend_transform(faiss.NormalizationTransform(P, 2.0))
        prefix.prepend_transform(faiss.RemapDimensionsTransform(D, P, False))  # the first P components
        codes = faiss.IndexScalarQuantizer(D, faiss.ScalarQuantizer.QT_8bit, faiss.METRIC_INNER_PRODUCT)
        refine = faiss.IndexRefine(prefix, codes)
        refine.k_factor = float(kf)
        outer = faiss.IndexPreTransform(refine)
        if "L2norm" in m["outer"]:
            outer.prepend_transform(faiss.NormalizationTransform(D, 2.0))
        outer.prepend_transform(faiss.PCAMatrix(d, D))
        # a round trip through faiss's serialisation: one index that owns all its parts (no SWIG references)
        return faiss.deserialize_index(faiss.serialize_index(outer))
    except RuntimeError as exc:
        raise AerolocError(f"faiss index '{factory}' cannot be built for dim {d}: {str(exc).splitlines()[0]}") from None


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
    """The index at ``path``, its vectors / inverted lists memory-mapped (see the module docstring); a two-stage
    index (``path`` + ``.rerank.json``) as a :class:`RerankIndex` over its store."""
    import faiss

    path = Path(path)
    if not path.is_file():
        raise AerolocError(f"{path}: index not found (rebuild with 'aeroloc build')")
    if _rerank_json(path).is_file():
        return RerankIndex.open(path)
    if _ivfdata(path).is_file():
        return faiss.read_index(str(path.resolve()))
    try:
        return faiss.read_index(str(path), faiss.IO_FLAG_MMAP_IFC)
    except RuntimeError:  # not a flat index: read it normally
        return faiss.read_index(str(path))


class RerankIndex:
    """A coarse faiss index whose ``candidates`` best ids per query are re-scored exactly: the inner product of
    the query with each candidate's row of the float16 ``.npy`` store, as exact ``Flat`` search scores it (the
    store's values in float32). Rows are read with ``os.preadv`` (runs of neighbouring ids in one call) into a
    buffer, not memory-mapped, so the store's pages are the kernel's cache, not this process's RAM.
    The top ``k`` equals exact search whenever the exact top ``k`` are among the candidates."""

    def __init__(self, coarse, store: Path, candidates: int, huge_pages: bool = True):
        import faiss

        self.coarse, self.store, self.candidates = coarse, Path(store), int(candidates)
        if not self.store.is_file():
            raise AerolocError(f"{self.store}: the descriptor store of the two-stage index is missing (rebuild)")
        mm = np.load(self.store, mmap_mode="r")  # the header only: no row is touched
        shape, dtype, fortran, self._offset = mm.shape, mm.dtype, not mm.flags.c_contiguous, mm.offset
        del mm
        if fortran or dtype != np.float16 or len(shape) != 2 or shape[0] != coarse.ntotal:
            raise AerolocError(
                f"{self.store}: store {shape} {dtype} does not match its index ({coarse.ntotal} rows, float16); rebuild"
            )
        self.ntotal, self.d = int(shape[0]), int(shape[1])
        self._projection = _Projection.of(coarse)
        self._fd = os.open(self.store, os.O_RDONLY)
        # the re-rank's scorer, kept: its code buffer is reused by every query (a fresh 6.5 MB buffer per query
        # paid ~1,600 page faults before the first row landed in it)
        self._scorer = faiss.IndexScalarQuantizer(self.d, faiss.ScalarQuantizer.QT_fp16, faiss.METRIC_INNER_PRODUCT)
        # the walk's random reads of the graph and codes on 2 MB pages (see aeroloc.retrieval.hugepages)
        self.huge_page_bytes = collapse_index(coarse) if huge_pages else 0

    @classmethod
    def open(cls, path: Path, huge_pages: bool = True) -> RerankIndex:
        import faiss

        meta = json.loads(_rerank_json(path).read_text())
        return cls(faiss.read_index(str(path)), path.parent / meta["store"], meta["candidates"], huge_pages)

    @property
    def ef_search(self) -> int | None:
        """The coarse HNSW's search breadth (None for a coarse index without a graph); a walk for ``R`` candidates
        keeps max(ef_search, R) nodes in its queue."""
        hnsw = _hnsw_or_none(self.coarse)
        return None if hnsw is None else int(hnsw.efSearch)

    @ef_search.setter
    def ef_search(self, ef: int) -> None:
        hnsw = _hnsw_or_none(self.coarse)
        if hnsw is None:
            raise AerolocError("the coarse index of this two-stage index has no HNSW graph (no efSearch)")
        hnsw.efSearch = int(ef)

    def rows(self, ids: np.ndarray) -> np.ndarray:
        """float16 store rows ``ids`` (sorted, unique), read in runs of consecutive ids."""
        out = np.empty((len(ids), self.d), np.float16)
        self._read_into(ids, memoryview(out).cast("B"))
        return out

    def _read_into(self, ids: np.ndarray, buf: memoryview) -> None:
        """Store rows ``ids`` (sorted, unique) into the bytes ``buf``, one ``preadv`` per run of consecutive ids."""
        if not len(ids):
            return
        row = self.d * 2
        breaks = np.flatnonzero(np.diff(ids) != 1) + 1
        for a, b in zip(np.r_[0, breaks].tolist(), np.r_[breaks, len(ids)].tolist()):
            want = (b - a) * row
            got = os.preadv(self._fd, [buf[a * row : b * row]], self._offset + int(ids[a]) * row)
            if got != want:
                raise AerolocError(f"{self.store}: short read ({got} of {want} bytes); the store was truncated")

    def _candidates(self, q: np.ndarray, r: int) -> np.ndarray:
        """The coarse index's ``r`` best ids per query. A few queries are projected one at a time by
        :class:`_Projection` (the PCA matrix in float16: half the bytes of faiss's float32 product, which a
        one-query product spends its time reading) and walk the graph behind the transforms; a batch goes
        through the coarse index's own (float32, BLAS) transforms."""
        if self._projection is None or len(q) >= SMALL_BATCH:
            return self.coarse.search(q, r)[1]
        return np.concatenate([self._projection.inner.search(self._projection(x), r)[1] for x in q])

    def search(self, q: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Scores are computed by a faiss float16 scalar-quantizer index over the candidates' raw rows (its
        codes are the rows' bytes, read straight into the index's code buffer; decoding with F16C is exact):
        25x faster than numpy's float16 conversion."""
        import faiss

        q = np.ascontiguousarray(q, dtype=np.float32)
        threads = faiss.omp_get_max_threads()
        # one thread for the re-rank (a few hundred rows per query) and for the coarse search of a few queries
        # (one PCA product and one graph walk each): OpenMP threads waiting for a core made a query 4x slower on
        # the busy machine (20 ms instead of 5 at 200 candidates, load 10; the PCA of one query 7.6 ms, not 2.8)
        if len(q) < SMALL_BATCH:
            faiss.omp_set_num_threads(1)
        try:
            cand = self._candidates(q, min(max(self.candidates, k), self.ntotal))
        finally:
            faiss.omp_set_num_threads(threads)
        scores = np.full((len(q), k), -np.inf, np.float32)
        ids = np.full((len(q), k), -1, np.int64)
        exact = self._scorer
        faiss.omp_set_num_threads(1)
        try:
            for i, c in enumerate(cand):
                c = np.unique(c[c >= 0])
                nbytes = len(c) * self.d * 2
                exact.codes.resize(nbytes)
                if nbytes:
                    self._read_into(c, memoryview(faiss.rev_swig_ptr(exact.codes.data(), nbytes)))
                exact.ntotal = len(c)
                s, pos = exact.search(q[i : i + 1], min(k, len(c)))
                scores[i, : pos.shape[1]], ids[i, : pos.shape[1]] = s[0], c[pos[0]]
        finally:
            faiss.omp_set_num_threads(threads)
        return scores, ids

    def __del__(self):
        with contextlib.suppress(AttributeError, OSError):
            os.close(self._fd)


class _Projection:
    """A coarse ``PCA…[,L2norm],<index>``'s transforms of one query with the PCA matrix held compactly, because a
    one-query product is bound by reading the matrix (1024 x 8192: 33 MB in float32): 8-bit rows, each with its
    own scale, multiplied by the query in bfloat16 (torch's weight-only int8 product: 8 MB read; 0.2 ms with the
    matrix in cache, 0.5 from RAM at 10^6 tiles, against 0.9 and 1.2 in float16); where torch lacks that product,
    the rows in float16 scored by a faiss float16 scalar-quantizer index (F16C). Then the PCA's bias and the
    normalisation. The 8-bit form moves a transformed query by ~1 % of its norm; on the real sets the
    candidates it finds are those of the float32 transform (recall@10 of exact unchanged, benchmarks/scale.py).
    ``inner`` is the index behind the transforms."""

    def __init__(self, pca, normalize: bool, inner):
        import faiss

        a = faiss.vector_to_array(pca.A).reshape(pca.d_out, pca.d_in)
        self.bias = faiss.vector_to_array(pca.b) if pca.have_bias else np.zeros(pca.d_out, np.float32)
        self.normalize, self.inner, self.d_out = normalize, inner, pca.d_out
        self._int8 = _int8_rows(a)
        if self._int8 is None:
            self.rows = faiss.IndexScalarQuantizer(pca.d_in, faiss.ScalarQuantizer.QT_fp16, faiss.METRIC_INNER_PRODUCT)
            self.rows.add(np.ascontiguousarray(a, dtype=np.float32))

    @classmethod
    def of(cls, coarse) -> _Projection | None:
        import faiss

        chain = _pca_chain_or_none(coarse)
        if chain is None or any(t.norm != 2.0 for t in chain[1:]):  # only the L2 normalisation is reproduced
            return None
        return cls(chain[0], len(chain) > 1, faiss.downcast_index(faiss.downcast_index(coarse).index))

    def __call__(self, x: np.ndarray) -> np.ndarray:
        """The transformed query ``x`` (one row) as a (1, d_out) float32 array."""
        x = np.ascontiguousarray(x, dtype=np.float32).reshape(1, -1)
        if self._int8 is not None:
            import torch

            rows, scales = self._int8
            with torch.inference_mode():
                y = torch._weight_int8pack_mm(torch.from_numpy(x).to(torch.bfloat16), rows, scales)
            y = y.float().numpy()[0]
        else:
            s, pos = self.rows.search(x, self.d_out)
            y = np.empty(self.d_out, np.float32)
            y[pos[0]] = s[0]
        y += self.bias
        if self.normalize:
            y /= max(float(np.linalg.norm(y)), 1e-30)
        return y[None]


def _int8_rows(a: np.ndarray):
    """(int8 rows, bfloat16 scales) of the matrix ``a`` for torch's weight-only int8 product (each row scaled by
    its largest magnitude / 127), or None where torch has no such product on the CPU, or where it does not give
    the 8-bit matrix's product (a private operator: its meaning is checked on one vector, not assumed)."""
    try:
        import torch

        scale = np.maximum(np.abs(a).max(axis=1), 1e-30) / 127
        q = np.clip(np.rint(a / scale[:, None]), -127, 127).astype(np.int8)
        rows, scales = torch.from_numpy(q), torch.from_numpy(scale.astype(np.float32)).to(torch.bfloat16)
        x = np.cos(np.arange(a.shape[1], dtype=np.float32))  # any vector whose bfloat16 form is close to it
        with torch.inference_mode():
            got = torch._weight_int8pack_mm(torch.from_numpy(x[None]).to(torch.bfloat16), rows, scales)
        want = (q.astype(np.float32) * scales.float().numpy()[:, None]) @ x
        if not np.allclose(got.float().numpy()[0], want, rtol=0.02, atol=0.02 * float(np.abs(want).max())):
            return None
        return rows, scales
    except (ImportError, AttributeError, RuntimeError, NotImplementedError):
        return None


def _hnsw_or_none(index):
    """The HNSW graph of ``index`` or of the index behind its transforms (and a prefix index's refinement),
    else None."""
    import faiss

    inner = faiss.downcast_index(index)
    while isinstance(inner, (faiss.IndexPreTransform, faiss.IndexRefine)):  # through transforms and refinements
        inner = faiss.downcast_index(inner.index if isinstance(inner, faiss.IndexPreTransform) else inner.base_index)
    return getattr(inner, "hnsw", None)


FLAT_MAX = 100_000  # exact search below this many tiles (16 KB/tile at 8192-d: 1.6 GB at the limit)
PCA_DIM = 256
TRAIN_MAX = 20_000  # training sample of an index without PCA (8192-d float32: 655 MB at most)
# HNSW search breadth: on real 8192-d effnet-vlad tiles HNSW32,SQ8 keeps recall@10 0.986-0.993 of exact at 256,
# 0.94-0.99 at 64 (benchmarks/scale.py); faiss's default 16 loses more
EF_SEARCH = 256
PCA_TRAIN_MAX = 4_000  # rows the PCA is fitted on (4000 x 8192 float32: 131 MB)
# above FLAT_MAX: a compact coarse index and an exact re-rank of its best RERANK_CANDIDATES from the store
COARSE = "PCA1024,L2norm,HNSW32,SQ8"
RERANK_CANDIDATES = 400
# HNSW graphs are built with efConstruction EF_CONSTRUCTION (faiss's default is 40): a graph built with a wider
# search links each tile to better neighbours, so a narrower walk finds the same candidates. On NAIP's 25,480
# real tiles (400 candidates) recall@10 of exact at efSearch 800/500/400: built at 40 0.983/0.979/0.978, at 160
# 0.986/0.984/0.982 (levir-tx, szada-hu >= 0.996 at every setting); the build costs ~4x the CPU of faiss's default
EF_CONSTRUCTION = 160
# a two-stage index's graph is walked with efSearch RERANK_EF x its candidates (500 for 400): with the graph
# above it keeps more of NAIP's exact top-10 than the default graph walked at 800 (0.984 vs 0.983), for less
# of the walk's random reads (benchmarks/scale.py)
RERANK_EF = 1.25
SMALL_BATCH = 8  # fewer queries than this are searched on one thread (see RerankIndex.search)
_RERANK = re.compile(r"^(?P<coarse>.+),Rerank(?P<r>\d+)$")


def choose_factory(n: int, dim: int) -> str:
    """Exact ``Flat`` under ``FLAT_MAX`` tiles; above, two-stage ``COARSE,Rerank<RERANK_CANDIDATES>``
    (:class:`RerankIndex`): RAM holds the coarse index (~1.3 KB/tile at 1024 dims) and the exact re-rank of its
    candidates restores the top (benchmarks/scale.py: recall@10 of exact on the real NAIP, levir-tx and szada-hu
    tiles; on NAIP's 25,480 tiles the exact top-400 by 1024 PCA components hold 0.99 of the exact top-10 for the
    photos, by 512 components 0.94). Descriptors of at most 1024 dims need no PCA: their coarse index is
    ``HNSW32,SQ8``. (HNSW32,SQ8 over the full 8192 dims also keeps recall but is 8.4 KB/tile in RAM; PCA + IVF
    keep only 0.19-0.58 of the exact top-10 for photos.)"""
    if n < FLAT_MAX:
        return "Flat"
    coarse = COARSE if dim > 1024 else "HNSW32,SQ8"
    return f"{coarse},Rerank{RERANK_CANDIDATES}"


def _rerank_json(path: Path) -> Path:
    return path.with_name(path.name + ".rerank.json")


def as_float32(rows: np.ndarray) -> np.ndarray:
    """``rows`` as C-contiguous float32, the same values; float16 rows are decoded by faiss (F16C: exact, ~25x
    faster than numpy's float16 conversion, which takes ~1 min per 10^9 values)."""
    rows = np.asarray(rows)
    if rows.dtype != np.float16 or rows.ndim != 2 or not len(rows):
        return np.ascontiguousarray(rows, dtype=np.float32)
    import faiss

    fp16 = faiss.IndexScalarQuantizer(rows.shape[1], faiss.ScalarQuantizer.QT_fp16, faiss.METRIC_INNER_PRODUCT)
    return fp16.sa_decode(np.ascontiguousarray(rows).view(np.uint8))


def _ivfdata(path: Path) -> Path:
    return path.with_name(path.name + ".ivfdata")


def _sample_rows(npy: Path, n_pick: int) -> np.ndarray:
    """A fixed random sample of ``n_pick`` rows of the store as float32, read in sorted order."""
    mm = np.load(npy, mmap_mode="r")
    pick = np.sort(np.random.default_rng(0).choice(mm.shape[0], min(n_pick, mm.shape[0]), replace=False))
    return as_float32(mm[pick])


def _train(index, npy: Path, n: int) -> None:
    """Train on fixed samples of the store. A ``PCA…`` chain (the PCA, optionally then ``L2norm``) fits its
    transform on at most ``PCA_TRAIN_MAX`` rows with a randomized SVD (:func:`fit_pca`: faiss's own PCA on
    8192-d descriptors took > 10 min) and the index after it on at most ``TRAIN_MAX`` rows already transformed;
    other indexes train on ``TRAIN_MAX`` rows."""
    import faiss

    if n < 40:
        raise AerolocError(f"faiss index needs training data; {n} descriptors is too few (use Flat)")
    _skip_polysemous_training(index)
    chain = _pca_chain_or_none(index)
    if chain is None:
        _train_on(index, _sample_rows(npy, TRAIN_MAX))
        return
    fit_pca(chain[0], _sample_rows(npy, PCA_TRAIN_MAX))
    sub = faiss.downcast_index(index).index
    _train_on(sub, _reduced_sample(chain, npy, TRAIN_MAX))
    index.is_trained = True


def _train_on(index, x: np.ndarray) -> None:
    """``index.train(x)`` with faiss's errors (too few points for the lists …) as one-line AerolocErrors."""
    try:
        index.train(x)
    except RuntimeError as exc:
        raise AerolocError(f"faiss index training failed on {len(x)} descriptors: {str(exc).splitlines()[0]}") from None


def _pca_chain_or_none(index):
    """The transforms of a ``PCA…[,L2norm],<index>`` factory (a pre-transform chain that starts with a PCA and
    is at most followed by a normalisation), else None."""
    import faiss

    index = faiss.downcast_index(index)
    if not isinstance(index, faiss.IndexPreTransform) or not 1 <= index.chain.size() <= 2:
        return None
    chain = [faiss.downcast_VectorTransform(index.chain.at(i)) for i in range(index.chain.size())]
    if not isinstance(chain[0], faiss.PCAMatrix) or not all(
        isinstance(t, faiss.NormalizationTransform) for t in chain[1:]
    ):
        return None
    return chain


def _reduced_sample(chain, npy: Path, n_pick: int, chunk: int = 2048) -> np.ndarray:
    """The fixed training sample of ``n_pick`` rows through the transforms ``chain``, chunk by chunk (never all
    of it at full dim)."""
    mm = np.load(npy, mmap_mode="r")
    pick = np.sort(np.random.default_rng(0).choice(mm.shape[0], min(n_pick, mm.shape[0]), replace=False))
    parts = []
    for s in range(0, len(pick), chunk):
        x = as_float32(mm[pick[s : s + chunk]])
        for t in chain:
            x = t.apply(x)
        parts.append(x)
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
    ``nprobe`` (IVF) and ``ef_search`` (HNSW) are saved with the index, so a search uses them; the coarse graph
    of a two-stage index is saved with at least ``RERANK_EF`` x its candidates; HNSW graphs are built with
    ``EF_CONSTRUCTION``.

    ``Flat`` is streamed to the file (:func:`_write_flat`) rather than filled in RAM: the exact index of 10^5
    8192-d tiles is 3.3 GB of float32, and holding it made the build's peak RSS grow with the map."""
    import faiss

    from aeroloc.retrieval.shards import iter_rows

    npy, path = Path(npy), Path(path)
    n, d = np.load(npy, mmap_mode="r").shape
    factory = choose_factory(n, d) if factory == "auto" else factory
    coarse, candidates = _split_rerank(factory)
    index = make_index(d, coarse)
    _ivfdata(path).unlink(missing_ok=True)
    _rerank_json(path).unlink(missing_ok=True)
    flat = faiss.downcast_index(index)
    if type(flat) in (faiss.IndexFlat, faiss.IndexFlatIP) and flat.metric_type == faiss.METRIC_INNER_PRODUCT:
        if candidates:
            raise AerolocError(f"'{factory}': an exact index needs no re-rank (use Flat)")
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
    hnsw = _hnsw_or_none(index)
    if hnsw is not None:
        hnsw.efConstruction = EF_CONSTRUCTION
        hnsw.efSearch = max(ef_search, round(RERANK_EF * candidates))
    for rows in iter_rows(npy, chunk):
        index.add(as_float32(rows))
    save_index(index, path)
    if candidates:  # after the index: a crash in between leaves an index the database does not register
        store = os.path.relpath(npy.resolve(), path.resolve().parent)
        atomic_write_text(_rerank_json(path), json.dumps({"store": store, "candidates": candidates}))
    return factory


def _split_rerank(factory: str) -> tuple[str, int]:
    """(coarse factory, candidates) of ``…,Rerank<R>``; (factory, 0) for a one-stage factory."""
    m = _RERANK.match(factory)
    if m is None:
        if "Rerank" in factory:
            raise AerolocError(f"'{factory}': the re-rank is written last, as ',Rerank<candidates>' (e.g. ,Rerank400)")
        return factory, 0
    if int(m["r"]) < 1:
        raise AerolocError(f"'{factory}': the re-rank needs >= 1 candidate")
    return m["coarse"], int(m["r"])


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
            f.write(as_float32(rows).astype("<f4", copy=False).tobytes())
    tmp.replace(path)


def _ivf_or_none(index):
    import faiss

    try:
        return faiss.extract_index_ivf(index)
    except RuntimeError:
        return None
