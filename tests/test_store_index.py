"""On-disk stores (resume, completeness, HDF5 round trip, encodings) and the Faiss index wrapper (exactness)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from aeroloc.core.errors import AerolocError
from aeroloc.core.io import config_key
from aeroloc.matching.store import FeatureStore
from aeroloc.retrieval.index import build_index, load_index, save_index, search
from aeroloc.retrieval.store import DescriptorStore


def unit_rows(n: int, dim: int, seed: int = 0) -> np.ndarray:
    x = np.random.default_rng(seed).standard_normal((n, dim)).astype(np.float32)
    return x / np.linalg.norm(x, axis=1, keepdims=True)


# --- DescriptorStore ----------------------------------------------------------------------------------------
def test_descriptor_store_resumes_after_interruption_and_equals_one_shot(tmp_path):
    x = unit_rows(10, 8)
    # one-shot reference
    ref = DescriptorStore(tmp_path / "ref", 10, 8)
    start, write, finish = ref.writer()
    assert start == 0
    write(x)
    finish()
    # interrupted: two batches flushed, then the process "dies" (writer dropped without finish)
    part = DescriptorStore(tmp_path / "part", 10, 8)
    start, write, _ = part.writer()
    write(x[:3])
    write(x[3:6])
    del write
    assert not part.complete
    with pytest.raises(AerolocError, match=r"incomplete|missing"):
        DescriptorStore.open_complete(tmp_path / "part")
    # a new writer (new process) starts at the flushed row and keeps the rows written before
    again = DescriptorStore(tmp_path / "part", 10, 8)
    start, write, finish = again.writer()
    assert start == 6
    write(x[6:])
    finish({"note": "resumed"})
    done = DescriptorStore.open_complete(tmp_path / "part")
    assert done.meta["note"] == "resumed" and done.meta["dtype"] == "float16"
    got = done.load(mmap=False)
    assert got.dtype == np.float16 and got.shape == (10, 8)
    np.testing.assert_array_equal(got, ref.load(mmap=False))
    np.testing.assert_allclose(got.astype(np.float32), x, atol=1e-3)  # float16 precision
    assert not (tmp_path / "part" / "progress.json").exists()


def test_descriptor_store_shape_change_starts_afresh_and_finish_checks_rows(tmp_path):
    s = DescriptorStore(tmp_path, 6, 4)
    _, write, finish = s.writer()
    write(unit_rows(2, 4))
    with pytest.raises(AerolocError, match="2 of 6"):
        finish()
    with pytest.raises(AerolocError, match="dim 4"):
        write(unit_rows(2, 5))
    # another shape (e.g. other tile count) must not reuse the 2 rows written for (6, 4)
    assert DescriptorStore(tmp_path, 7, 4).writer()[0] == 0


def test_half_written_store_is_refused(tmp_path):
    s = DescriptorStore(tmp_path, 4, 3)
    _, write, _ = s.writer()
    write(unit_rows(4, 3))  # every row there, but finish() never ran: no meta.json
    assert (tmp_path / "descriptors.npy").is_file() and not (tmp_path / "meta.json").exists()
    with pytest.raises(AerolocError, match=str(tmp_path.name)):
        DescriptorStore.open_complete(tmp_path)
    # a meta.json that does not say complete is refused too
    (tmp_path / "meta.json").write_text(json.dumps({"n": 4, "dim": 3, "complete": False}))
    with pytest.raises(AerolocError, match="incomplete"):
        DescriptorStore.open_complete(tmp_path)
    with pytest.raises(AerolocError):
        DescriptorStore.open_complete(tmp_path / "nowhere")


def test_config_key_changes_with_any_part():
    a = config_key("xfeat-vlad", {"n_clusters": 64}, "tiles1")
    assert a == config_key("xfeat-vlad", {"n_clusters": 64}, "tiles1")
    assert a != config_key("xfeat-vlad", {"n_clusters": 128}, "tiles1")
    assert a != config_key("xfeat-vlad", {"n_clusters": 64}, "tiles2")


# --- FeatureStore -------------------------------------------------------------------------------------------
def features(n: int, seed: int) -> dict:
    rng = np.random.default_rng(seed)
    return {
        "keypoints": (rng.random((n, 2)) * 500).astype(np.float32),
        "descriptors": rng.standard_normal((n, 64)).astype(np.float32),
        "scores": rng.random(n).astype(np.float32),
        "image_size": np.array([512, 384], np.int64),
        "scale": np.float64(2.0),
    }


def test_feature_store_round_trip(tmp_path):
    store = FeatureStore(tmp_path / "f.h5")
    assert store.names() == set()
    a, b = features(100, 1), features(7, 2)
    store.write_many({"r000c000": a, "r000c001": b})
    store.write_many({"r001c000": features(0, 3)})  # a tile without keypoints is a valid entry
    assert store.names() == {"r000c000", "r000c001", "r001c000"}
    with store.reader() as r:
        got = r.get("r000c000")
        empty = r.get("r001c000")
        with pytest.raises(AerolocError, match="r009c009"):
            r.get("r009c009")
    np.testing.assert_array_equal(got["keypoints"], a["keypoints"])  # keypoints exact (float32)
    assert got["keypoints"].dtype == np.float32
    assert got["descriptors"].dtype == np.float32 and got["scores"].dtype == np.float32
    np.testing.assert_array_equal(got["descriptors"], a["descriptors"].astype(np.float16).astype(np.float32))
    np.testing.assert_allclose(got["descriptors"], a["descriptors"], rtol=1e-3, atol=1e-3)
    np.testing.assert_array_equal(got["image_size"], [512, 384])
    assert float(got["scale"]) == 2.0
    assert empty["keypoints"].shape == (0, 2) and empty["descriptors"].shape == (0, 64)
    # on disk: float16 descriptors
    import h5py

    with h5py.File(tmp_path / "f.h5", "r") as f:
        assert f["r000c000/descriptors"].dtype == np.float16
    assert store.bytes_per_item() > 0


def test_feature_store_group_visible_only_after_complete_write(tmp_path, monkeypatch):
    import h5py

    store = FeatureStore(tmp_path / "f.h5")
    store.write_many({"done": features(5, 0)})
    real = h5py.Group.create_dataset
    calls = {"n": 0}

    def dying(self, name, *a, **kw):  # crash while the second dataset of a tile is being written
        calls["n"] += 1
        if calls["n"] == 2:
            raise KeyboardInterrupt("simulated crash")
        return real(self, name, *a, **kw)

    monkeypatch.setattr(h5py.Group, "create_dataset", dying)
    with pytest.raises(KeyboardInterrupt):
        store.write_many({"half": features(5, 1)})
    monkeypatch.setattr(h5py.Group, "create_dataset", real)
    assert store.names() == {"done"}  # the half-written tile is not listed (it stays under its temp name)
    store.write_many({"half": features(5, 1)})  # rewriting it works and replaces the leftover
    assert store.names() == {"done", "half"}
    with store.reader() as r:
        np.testing.assert_array_equal(r.get("half")["keypoints"], features(5, 1)["keypoints"])


def test_unit_norm_descriptors_stored_as_int8_within_one_step(tmp_path):
    import h5py

    store = FeatureStore(tmp_path / "f.h5")
    f = features(300, 4)
    f["descriptors"] = unit_rows(300, 64, 4)
    f["descriptors"][0] = np.eye(64, dtype=np.float32)[3] * -1  # a component at -1: the clip edge
    f["keypoints"] = (np.random.default_rng(4).integers(0, 1024, (300, 2)) + 0.5).astype(np.float32)
    store.write_many({"t": f})
    with h5py.File(tmp_path / "f.h5", "r") as h:
        d = h["t/descriptors"]
        assert d.dtype == np.int8 and d.attrs["quant_scale"] == 127 and d[0, 3] == -127
        assert h["t/keypoints"].dtype == np.float16  # half-pixel grid below 1024: float16 holds it exactly
    with store.reader() as r:
        got = r.get("t")
    assert got["descriptors"].dtype == np.float32 and got["keypoints"].dtype == np.float32
    assert np.abs(got["descriptors"] - f["descriptors"]).max() <= 0.5 / 127 + 1e-7
    assert np.abs(np.linalg.norm(got["descriptors"], axis=1) - 1).max() <= 1e-2
    np.testing.assert_array_equal(got["keypoints"], f["keypoints"])  # lossless
    np.testing.assert_allclose(got["scores"], f["scores"], atol=5e-4)


def test_a_tile_without_keypoints_and_scalar_fields_read_back_as_written(tmp_path):
    """The low-level group read (FeatureStore.read_group) gives empty arrays their shape and dtype, and 0-d
    fields numpy scalars of their own type, as the arrays were written."""
    store = FeatureStore(tmp_path / "f.h5")
    empty = {
        "keypoints": np.zeros((0, 2), np.float32),
        "descriptors": np.zeros((0, 64), np.float32),
        "scale": np.float64(2.5),
        "rot_k": np.int64(3),
        "orig_size": np.array([1280, 1230], np.int64),
    }
    store.write_many({"t": empty})
    with store.reader() as r:
        got = r.get("t")
    assert got["keypoints"].shape == (0, 2) and got["descriptors"].shape == (0, 64)
    assert got["keypoints"].dtype == np.float32 and got["descriptors"].dtype == np.float32
    assert type(got["scale"]) is np.float64 and got["scale"] == 2.5
    assert type(got["rot_k"]) is np.int64 and got["rot_k"] == 3
    np.testing.assert_array_equal(got["orig_size"], [1280, 1230])


def test_not_unit_norm_descriptors_keep_float16(tmp_path):
    import h5py

    x = unit_rows(50, 128, 5)
    x[7] *= 1.02  # one row off unit norm by more than 1e-2 is enough to keep the whole tile float16
    store = FeatureStore(tmp_path / "f.h5")
    store.write_many({"t": {"descriptors": x}, "sift": {"descriptors": x * 300}})
    with h5py.File(tmp_path / "f.h5", "r") as h:
        for name in ("t", "sift"):
            assert h[name]["descriptors"].dtype == np.float16 and "quant_scale" not in h[name]["descriptors"].attrs
    with store.reader() as r:
        np.testing.assert_array_equal(r.get("t")["descriptors"], x.astype(np.float16).astype(np.float32))
        np.testing.assert_array_equal(r.get("sift")["descriptors"], (x * 300).astype(np.float16).astype(np.float32))


def test_format1_group_still_reads(tmp_path):
    """A store written before int8 descriptors (float16, no quant_scale attribute) reads as before."""
    import h5py

    f = features(20, 6)
    f["descriptors"] = unit_rows(20, 64, 6)
    with h5py.File(tmp_path / "old.h5", "w") as h:
        g = h.create_group("r000c000")
        for k, v in f.items():
            g.create_dataset(k, data=v.astype(np.float16) if k in ("descriptors", "scores") else v)
    with FeatureStore(tmp_path / "old.h5").reader() as r:
        got = r.get("r000c000")
    assert got["descriptors"].dtype == np.float32 and got["scores"].dtype == np.float32
    np.testing.assert_array_equal(got["descriptors"], f["descriptors"].astype(np.float16).astype(np.float32))
    np.testing.assert_array_equal(got["keypoints"], f["keypoints"])
    assert float(got["scale"]) == 2.0


def test_feature_format_is_part_of_the_local_store_key(monkeypatch):
    import types

    from aeroloc.matching import features as localfeatures
    from aeroloc.matching.registry import rerank_conf

    db, conf = types.SimpleNamespace(tiles_hash=lambda: "tiles"), rerank_conf("xfeat-lighterglue")
    now = localfeatures.local_key(db, "xfeat-lighterglue", conf)
    monkeypatch.setattr(localfeatures, "FEATURE_FORMAT", 1)
    assert localfeatures.local_key(db, "xfeat-lighterglue", conf) != now


def test_xfeat_tile_fits_200kb_and_stored_descriptors_match_like_float32(naip_tiles_db, tmp_path):
    """Real NAIP tile, default re-ranker's extractor: bytes on disk, and the screen's mutual NN after the round trip."""
    import cv2

    from aeroloc.localization.cascade import mutual_nn
    from aeroloc.matching.features import extract
    from aeroloc.matching.registry import build_reranker
    from aeroloc.retrieval.database import Database

    extractor, _ = build_reranker("xfeat-lighterglue", "cpu")
    tile = Database(naip_tiles_db).tile_image("r002c002")
    h, w = tile.shape[:2]
    moved = cv2.warpAffine(tile, cv2.getRotationMatrix2D((w / 2 + 18, h / 2 - 11), 25, 1.0), (w, h))
    a, b = extract(extractor, tile, 512), extract(extractor, moved, 512)
    assert len(a["keypoints"]) == 2048  # a full tile: the size bound is about the real cap
    solo = FeatureStore(tmp_path / "solo.h5")
    solo.write_many({"tile": a})
    assert solo.bytes_per_item() <= 200_000
    store = FeatureStore(tmp_path / "f.h5")
    store.write_many({"tile": a, "moved": b})
    with store.reader() as r:
        sa, sb = r.get("tile"), r.get("moved")
    np.testing.assert_array_equal(sa["keypoints"], a["keypoints"])
    ref = {tuple(m) for m in mutual_nn(a["descriptors"], b["descriptors"], 0.7)}
    got = {tuple(m) for m in mutual_nn(sa["descriptors"], sb["descriptors"], 0.7)}
    assert len(ref) >= 300, f"only {len(ref)} float32 matches: not a meaningful comparison"
    agree = len(ref & got) / max(len(ref), len(got))
    assert agree >= 0.95, f"stored descriptors agree on {agree:.3f} of mutual-NN pairs"


# --- index ----------------------------------------------------------------------------------------------------
def test_flat_inner_product_is_exact():
    db, q = unit_rows(200, 32, 1), unit_rows(5, 32, 2)
    index = build_index(db, "Flat")
    scores, ids = search(index, q, 10)
    dots = q @ db.T
    expected = np.argsort(-dots, axis=1)[:, :10]
    np.testing.assert_array_equal(ids, expected)
    np.testing.assert_allclose(scores, np.take_along_axis(dots, expected, 1), atol=1e-5)
    # one query as a 1-d vector works too
    _s1, i1 = search(index, q[0], 3)
    np.testing.assert_array_equal(i1[0], expected[0, :3])


def test_k_larger_than_ntotal_returns_all():
    db = unit_rows(7, 16)
    _scores, ids = search(build_index(db), db[:2], 50)
    assert ids.shape == (2, 7) and sorted(ids[0]) == list(range(7)) and (ids >= 0).all()
    assert ids[0, 0] == 0 and ids[1, 0] == 1  # each vector is its own nearest neighbour
    with pytest.raises(AerolocError, match=">= 1"):
        search(build_index(db), db[:1], 0)


@pytest.mark.parametrize("factory", ["HNSW32", "IVF16,PQ8"])
def test_factory_strings_build_and_search(factory):
    db = unit_rows(1000, 32, 3)
    index = build_index(db, factory)
    assert index.ntotal == 1000 and index.is_trained
    # querying with database vectors: an approximate index still finds most of them first
    q = db[:50]
    _, ids = search(index, q, 5)
    assert ids.shape == (50, 5)
    self_hit = np.mean([i in row for i, row in enumerate(ids)])
    assert self_hit >= 0.8, f"{factory}: only {self_hit:.2f} of database vectors find themselves in top-5"


def test_bad_factory_and_too_little_training_data():
    db = unit_rows(20, 16)
    with pytest.raises(AerolocError, match="NoSuchIndex"):
        build_index(db, "NoSuchIndex")
    with pytest.raises(AerolocError, match="training"):
        build_index(db, "IVF16,PQ8")


def test_save_load_round_trip(tmp_path):
    db, q = unit_rows(300, 24, 4), unit_rows(3, 24, 5)
    index = build_index(db, "HNSW32")
    save_index(index, tmp_path / "index.faiss")
    assert not (tmp_path / "index.faiss.part").exists()
    back = load_index(tmp_path / "index.faiss")
    assert back.ntotal == 300
    for a, b in zip(search(index, q, 8), search(back, q, 8)):
        np.testing.assert_array_equal(a, b)
    with pytest.raises(AerolocError, match="not found"):
        load_index(tmp_path / "missing.faiss")


def test_local_store_key_follows_the_tile_features_not_the_reranking_settings():
    """Thresholds, rotations and geometry change how stored features are used, not the features: same store.
    The extractor's conf and the tiles' working side change the features: another store."""
    import types

    from aeroloc.matching import features as localfeatures
    from aeroloc.matching.registry import rerank_conf

    db = types.SimpleNamespace(tiles_hash=lambda: "tiles")
    key = localfeatures.local_key(db, "xfeat-lighterglue", rerank_conf("xfeat-lighterglue"))
    same = rerank_conf(
        "xfeat-lighterglue",
        {"rotations": [0], "min_inliers": 50, "geometry": "homography", "max_verify": 1, "matcher": {"min_conf": 0.5}},
    )
    assert localfeatures.local_key(db, "xfeat-lighterglue", same) == key
    for other in ({"tile_side": 384}, {"extractor": {"max_keypoints": 1024}}):
        assert localfeatures.local_key(db, "xfeat-lighterglue", rerank_conf("xfeat-lighterglue", other)) != key


def test_choose_factory_by_size():
    from aeroloc.retrieval.index import choose_factory

    assert choose_factory(35, 8192) == choose_factory(99_999, 8192) == "Flat"
    # above: a compact coarse index and an exact re-rank of its candidates from the store
    assert choose_factory(100_000, 8192) == choose_factory(10**6, 8192) == "PCA1024,L2norm,HNSW32,SQ8,Rerank400"
    assert choose_factory(10**6, 128) == "HNSW32,SQ8,Rerank400"  # small descriptors need no PCA


@pytest.mark.parametrize("factory", ["Flat", "IVF16,SQ8", "PCA32,IVF16,SQ8"])
def test_index_filled_chunk_by_chunk_from_the_store_is_memory_mapped(tmp_path, factory):
    """Built from the .npy store in chunks, read back mapped (flat vectors or on-disk IVF lists): same answers
    as the same index built in memory; the exact one equals brute force."""
    import faiss

    from aeroloc.retrieval.index import build_index_from_store

    rng = np.random.default_rng(1)
    x = rng.standard_normal((3000, 64)).astype(np.float32)
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    np.save(tmp_path / "d.npy", x.astype(np.float16))
    used = build_index_from_store(tmp_path / "d.npy", tmp_path / "index.faiss", factory, nprobe=16, chunk=700)
    assert used == factory
    assert (tmp_path / "index.faiss.ivfdata").is_file() == ("IVF" in factory)
    back = load_index(tmp_path / "index.faiss")
    assert back.ntotal == 3000
    q = x[:50]
    _, got = search(back, q, 10)
    ref = build_index(np.load(tmp_path / "d.npy").astype(np.float32), factory)
    if "IVF" in factory:
        faiss.extract_index_ivf(ref).nprobe = 16
    _, want = search(ref, q, 10)
    overlap = np.mean([len(set(a) & set(b)) / 10 for a, b in zip(got, want)])
    assert overlap >= (1.0 if factory == "Flat" else 0.9), overlap
    assert (got[:, 0] == np.arange(50)).mean() >= 0.9  # a stored vector finds itself first


def test_exact_index_streamed_to_disk_is_the_file_faiss_writes(tmp_path, monkeypatch):
    """The Flat index is written chunk by chunk without being held in RAM (faiss never gets the rows): the file
    has exactly the bytes faiss writes for the same index built in memory, and reads back (memory-mapped) with
    the same answers."""
    import faiss

    from aeroloc.retrieval import index as index_mod
    from aeroloc.retrieval.index import build_index_from_store

    def no_add(self, x):
        raise AssertionError("the exact index was filled in RAM")

    monkeypatch.setattr(faiss.IndexFlat, "add", no_add)
    monkeypatch.setattr(faiss.IndexFlatIP, "add", no_add)
    assert index_mod.build_index_from_store is build_index_from_store

    x = unit_rows(1000, 48, seed=3).astype(np.float16)
    np.save(tmp_path / "d.npy", x)
    (tmp_path / "index.faiss.ivfdata").write_bytes(b"stale")  # an earlier IVF build's lists: removed
    assert build_index_from_store(tmp_path / "d.npy", tmp_path / "index.faiss", "Flat", chunk=300) == "Flat"
    monkeypatch.undo()
    want = faiss.serialize_index(build_index(x.astype(np.float32), "Flat")).tobytes()
    assert (tmp_path / "index.faiss").read_bytes() == want
    assert not (tmp_path / "index.faiss.ivfdata").exists()
    _, ids = search(load_index(tmp_path / "index.faiss"), x[:20].astype(np.float32), 5)
    assert (ids[:, 0] == np.arange(20)).all()


def test_pca_fitted_by_randomized_svd_matches_faiss_pca():
    """fit_pca (a randomized SVD on a sample, seconds at 8192-d) keeps the variance faiss's exact PCA keeps and
    spans the same leading subspace, on descriptors with a decaying spectrum like real ones."""
    import faiss

    from aeroloc.retrieval.index import fit_pca

    rng = np.random.default_rng(4)
    x = (rng.standard_normal((2000, 256)) * (1.0 / np.arange(1, 257)) ** 0.7).astype(np.float32)
    x = x @ np.linalg.qr(rng.standard_normal((256, 256)))[0].astype(np.float32)
    ours, ref = faiss.PCAMatrix(256, 32), faiss.PCAMatrix(256, 32)
    fit_pca(ours, x)
    ref.train(x)
    a, b = ours.apply(x), ref.apply(x)
    assert np.sum(a**2) >= 0.99 * np.sum(b**2)  # variance kept
    ua = faiss.vector_to_array(ours.A).reshape(32, 256)[:16]
    ub = faiss.vector_to_array(ref.A).reshape(32, 256)[:16]
    assert np.linalg.svd(ua @ ub.T, compute_uv=False).min() > 0.99  # the same 16 leading directions


def test_hnsw_from_the_store_keeps_its_search_breadth(tmp_path):
    """An HNSW index built from the store is saved with ``ef_search`` (faiss's default 16 loses recall on real
    8192-d tiles), so a search after load_index uses it; it agrees with exact search on most neighbours."""
    import faiss

    from aeroloc.retrieval.index import EF_SEARCH, build_index_from_store

    x = unit_rows(1500, 64, seed=5)
    np.save(tmp_path / "d.npy", x.astype(np.float16))
    assert build_index_from_store(tmp_path / "d.npy", tmp_path / "i.faiss", "HNSW32,SQ8", chunk=400) == "HNSW32,SQ8"
    back = load_index(tmp_path / "i.faiss")
    assert faiss.downcast_index(back).hnsw.efSearch == EF_SEARCH
    x16 = np.load(tmp_path / "d.npy").astype(np.float32)
    _, got = search(back, x16[:40], 10)
    _, want = search(build_index(x16, "Flat"), x16[:40], 10)
    assert np.mean([len(set(a) & set(b)) / 10 for a, b in zip(got, want)]) >= 0.9


def clustered_rows(n: int, dim: int, seed: int = 0) -> np.ndarray:
    """Unit rows around 40 centres with a decaying spectrum (like real descriptors: PCA keeps the clusters)."""
    rng = np.random.default_rng(seed)
    scale = (1.0 / np.arange(1, dim + 1)) ** 0.5
    centres = rng.standard_normal((40, dim)) * scale
    x = centres[rng.integers(0, 40, n)] + 0.6 * rng.standard_normal((n, dim)) * scale
    return (x / np.linalg.norm(x, axis=1, keepdims=True)).astype(np.float32)


def _store(tmp_path, x) -> tuple:
    np.save(tmp_path / "d.npy", x.astype(np.float16))
    return tmp_path / "d.npy", np.load(tmp_path / "d.npy").astype(np.float32)


def test_two_stage_index_scores_its_candidates_exactly_from_the_store_without_mapping_it(tmp_path):
    """PCA + HNSW over 8-bit codes finds candidates; each returned score is the exact inner product with the
    store's row (what Flat computes), best first; with as many candidates as tiles the answer is exact search's;
    with a few it keeps most of the exact top-10 and beats the coarse index alone. The store is read, not
    memory-mapped (its pages never count in the process's RAM)."""
    import faiss

    from aeroloc.retrieval.index import RerankIndex, build_index_from_store

    npy, x16 = _store(tmp_path, clustered_rows(3000, 256, seed=1))
    q = x16[:40] + 0.05 * unit_rows(40, 256, seed=9)
    _, want = search(build_index(x16, "Flat"), q, 10)
    recalls = {}
    for r in (3000, 60):
        f = f"PCA32,L2norm,HNSW32,SQ8,Rerank{r}"
        assert build_index_from_store(npy, tmp_path / "i.faiss", f, chunk=700) == f
        index = load_index(tmp_path / "i.faiss")
        assert isinstance(index, RerankIndex) and index.ntotal == 3000 and index.candidates == r
        scores, ids = search(index, q, 10)
        np.testing.assert_allclose(scores, np.take_along_axis(q @ x16.T, ids, 1), rtol=0, atol=1e-5)
        assert (np.diff(scores, axis=1) <= 0).all()
        recalls[r] = np.mean([len(set(a) & set(b)) / 10 for a, b in zip(ids, want)])
        assert str(npy.resolve()) not in Path("/proc/self/maps").read_text()
    assert recalls[3000] == 1.0
    coarse = faiss.read_index(str(tmp_path / "i.faiss"))  # the coarse stage alone
    _, alone = coarse.search(q, 10)
    alone_recall = np.mean([len(set(a) & set(b)) / 10 for a, b in zip(alone, want)])
    assert recalls[60] >= 0.9 and recalls[60] > alone_recall, (recalls, alone_recall)


def test_two_stage_index_bad_input(tmp_path):
    """A re-rank that is not last, has no candidates or follows an exact index is refused in one line; so is
    a two-stage index whose store is gone or no longer matches it; a rebuild with another factory drops the
    re-rank."""
    from aeroloc.retrieval.index import build_index_from_store

    npy, _ = _store(tmp_path, clustered_rows(500, 64, seed=2))
    for factory, match in [
        ("HNSW32,Rerank0", ">= 1 candidate"),
        ("HNSW32,Rerank", "written last"),
        ("Rerank50,HNSW32", "written last"),
        ("Flat,Rerank50", "needs no re-rank"),
    ]:
        with pytest.raises(AerolocError, match=match):
            build_index_from_store(npy, tmp_path / "i.faiss", factory)
    build_index_from_store(npy, tmp_path / "i.faiss", "HNSW32,SQ8,Rerank50")
    load_index(tmp_path / "i.faiss")
    np.save(npy, clustered_rows(499, 64, seed=2).astype(np.float16))
    with pytest.raises(AerolocError, match="does not match its index"):
        load_index(tmp_path / "i.faiss")
    npy.unlink()
    with pytest.raises(AerolocError, match="store of the two-stage index is missing"):
        load_index(tmp_path / "i.faiss")
    _store(tmp_path, clustered_rows(500, 64, seed=2))
    build_index_from_store(npy, tmp_path / "i.faiss", "HNSW32,SQ8")
    assert not (tmp_path / "i.faiss.rerank.json").exists()
    assert not hasattr(load_index(tmp_path / "i.faiss"), "candidates")


def test_float16_rows_decoded_by_faiss_are_numpys_values():
    """as_float32 (faiss's F16C decoding, used wherever the store's rows are read) gives numpy's float32 value
    for every float16 bit pattern: normal, subnormal, zeros of both signs, infinities (NaNs stay NaN)."""
    from aeroloc.retrieval.index import as_float32

    every = np.arange(65536, dtype=np.uint16).view(np.float16).reshape(256, 256)
    got, want = as_float32(every), every.astype(np.float32)
    assert got.dtype == np.float32 and got.flags.c_contiguous
    nan = np.isnan(want)
    assert (np.isnan(got) == nan).all()
    assert (got[~nan].view(np.uint32) == want[~nan].view(np.uint32)).all()  # bit for bit, -0.0 included


def test_a_private_int8_product_that_does_not_give_the_matrix_product_is_not_used(monkeypatch):
    """torch's weight-only int8 product is a private operator: the 8-bit rows are used only when it gives their
    product with a vector (to bfloat16 rounding), else the float16 rows are."""
    import torch

    from aeroloc.retrieval.index import _int8_rows

    a = np.random.default_rng(0).standard_normal((64, 256)).astype(np.float32)
    rows, scales = _int8_rows(a)
    x = np.random.default_rng(1).standard_normal(256).astype(np.float32)
    with torch.inference_mode():
        got = torch._weight_int8pack_mm(torch.from_numpy(x[None]).to(torch.bfloat16), rows, scales).float().numpy()
    np.testing.assert_allclose(got[0], a @ x, atol=0.03 * np.abs(a @ x).max())  # 8-bit rows: ~1 % of the largest
    real = torch._weight_int8pack_mm
    monkeypatch.setattr(torch, "_weight_int8pack_mm", lambda x, w, s: real(x, w, s) * 2)
    assert _int8_rows(a) is None  # scaled twice over: refused
    monkeypatch.setattr(torch, "_weight_int8pack_mm", lambda x, w, s: real(x, w.flip(0), s))
    assert _int8_rows(a) is None  # rows in another order: refused


@pytest.mark.parametrize("form", ["int8", "float16"])
def test_two_stage_single_query_projects_with_a_compact_pca_matrix(tmp_path, monkeypatch, form):
    """A query searched alone is projected by the PCA matrix held compactly (8-bit rows with torch's
    weight-only int8 product, or float16 rows where torch lacks it: fewer bytes than the float32 product a
    one-query search is bound by): its transformed vector is faiss's float32 transform to the form's rounding,
    it finds the candidates the batch path finds, and its scores stay the exact inner products with the store's
    rows; the coarse graph's search breadth (1.25x the candidates, at least EF_SEARCH) can be read and set, and
    is refused for a coarse index without a graph."""
    import faiss

    from aeroloc.retrieval import index as index_module
    from aeroloc.retrieval.index import _pca_chain_or_none, build_index_from_store

    if form == "float16":
        monkeypatch.setattr(index_module, "_int8_rows", lambda a: None)
    npy, x16 = _store(tmp_path, clustered_rows(3000, 256, seed=3))
    q = x16[:30] + 0.05 * unit_rows(30, 256, seed=4)
    build_index_from_store(npy, tmp_path / "i.faiss", "PCA32,L2norm,HNSW32,SQ8,Rerank60", chunk=700)
    index = load_index(tmp_path / "i.faiss")
    proj = index._projection
    assert (proj._int8 is not None) == (form == "int8")  # torch's int8 product exists on this machine
    want = q
    for t in _pca_chain_or_none(index.coarse):
        want = t.apply(want)
    got = np.concatenate([proj(x) for x in q])
    assert got.shape == want.shape == (30, 32)
    np.testing.assert_allclose(np.linalg.norm(got, axis=1), 1.0, atol=1e-5)
    # the form's rounding of the matrix (8 bits: ~1 % of the unit vector; float16: ~1e-4), not another transform
    err = np.linalg.norm(got - want, axis=1).max()
    assert (1e-3 < err < 0.03) if form == "int8" else (1e-7 < np.abs(got - want).max() < 2e-3)
    single = [index.search(x[None], 10) for x in q]
    ids1 = np.concatenate([i for _, i in single])
    s1 = np.concatenate([s for s, _ in single])
    np.testing.assert_allclose(s1, np.take_along_axis(q @ x16.T, ids1, 1), rtol=0, atol=1e-5)
    _, batch = index.search(q, 10)  # 30 queries: faiss's float32 transforms
    assert np.mean([len(set(a) & set(b)) / 10 for a, b in zip(ids1, batch)]) >= 0.97
    assert index.ef_search == 256  # EF_SEARCH: more than 1.25 x the 60 candidates
    graph = faiss.downcast_index(faiss.downcast_index(index.coarse).index).hnsw
    assert graph.efConstruction == 160  # EF_CONSTRUCTION, saved with the graph (faiss's default is 40)
    build_index_from_store(npy, tmp_path / "k.faiss", "PCA32,L2norm,HNSW32,SQ8,Rerank240", chunk=700)
    assert load_index(tmp_path / "k.faiss").ef_search == 300  # the walk keeps 1.25 x the candidates
    index.ef_search = 90
    assert faiss.downcast_index(faiss.downcast_index(index.coarse).index).hnsw.efSearch == 90
    build_index_from_store(npy, tmp_path / "j.faiss", "PCA32,IVF16,SQ8,Rerank60")
    other = load_index(tmp_path / "j.faiss")
    assert other.ef_search is None and other._projection is not None
    with pytest.raises(AerolocError, match="no HNSW graph"):
        other.ef_search = 90
    np.testing.assert_allclose(other.search(q[:1], 5)[0], np.sort(q[:1] @ x16.T)[:, ::-1][:, :5], atol=1e-5)


def test_prefix_index_walks_the_leading_components_and_refines_with_all_of_them(tmp_path):
    """``PCA<D>,L2norm,Prefix<P>,<graph>,Refine<F>``: the graph holds only the first P of the D components (its
    vectors are P-dimensional), the 8-bit codes of all D re-score its F x k best, so the coarse answer is ranked
    like the D-component projection's (better than the P-component graph alone); behind a ``Rerank`` the
    scores are the store's exact inner products. The parts, their sizes and the refine factor survive the file;
    the graph's breadth can be set through the refinement. A prefix as long as the PCA is refused in one line."""
    import faiss

    from aeroloc.retrieval.index import _hnsw_or_none, build_index_from_store, make_index

    npy, x16 = _store(tmp_path, clustered_rows(3000, 256, seed=5))
    q = x16[:40] + 0.05 * unit_rows(40, 256, seed=6)
    _, want = search(build_index(x16, "Flat"), q, 10)

    def recall(ids):
        return np.mean([len(set(a) & set(b)) / 10 for a, b in zip(ids, want)])

    f = "PCA64,L2norm,Prefix16,HNSW32,SQ8,Refine8,Rerank40"
    assert build_index_from_store(npy, tmp_path / "i.faiss", f, chunk=700) == f
    coarse = faiss.read_index(str(tmp_path / "i.faiss"))  # read as its own class (IndexPreTransform)
    refine = faiss.downcast_index(coarse.index)
    assert isinstance(refine, faiss.IndexRefine) and refine.k_factor == 8 and refine.ntotal == 3000
    prefix = faiss.downcast_index(refine.base_index)
    assert prefix.chain.size() == 2 and faiss.downcast_index(prefix.index).d == 16
    assert faiss.downcast_index(refine.refine_index).d == 64
    index = load_index(tmp_path / "i.faiss")
    scores, ids = search(index, q, 10)
    np.testing.assert_allclose(scores, np.take_along_axis(q @ x16.T, ids, 1), rtol=0, atol=1e-5)
    _, refined = coarse.search(q, 10)
    refine.k_factor = 1.0  # the graph's own order over the 16 leading components
    _, graph_only = coarse.search(q, 10)
    assert recall(ids) >= 0.9 and recall(refined) > recall(graph_only), (
        recall(ids),
        recall(refined),
        recall(graph_only),
    )
    index.ef_search = 77
    assert _hnsw_or_none(index.coarse).efSearch == 77
    with pytest.raises(AerolocError, match="prefix must be shorter"):
        make_index(256, "PCA64,L2norm,Prefix64,HNSW32,SQ8,Refine8")
