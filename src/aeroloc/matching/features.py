"""Local features at a working resolution, with rotations, and the per-database feature store.

Matchers work best when query and tile show the ground at a similar scale, so both are resized so that their
longer side is ``side`` pixels before extraction (NAIP tiles are ~170-260 px at 5 m/px and gain from
upsampling; drone photos are ~3x finer than an orthomosaic and gain from downsampling). Keypoints are kept in the
frame the extractor saw and mapped back (``to_original``) for geometry, so homographies relate original images.
Query rotations (multiples of 90°) let upright-only matchers handle photos taken at any heading.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from aeroloc.core.frames import resize, resize_to_side
from aeroloc.core.images import read_image, valid_mask
from aeroloc.core.io import config_key
from aeroloc.matching.store import FEATURE_FORMAT, FeatureStore


def _rot90_points(xy: np.ndarray, k: int, w: int, h: int) -> np.ndarray:
    """Map points from an image rotated by k*90° counter-clockwise (np.rot90) back to the original (w x h)."""
    x, y = xy[:, 0], xy[:, 1]
    k %= 4
    if k == 0:
        return xy
    if k == 1:  # rotated is h x w: (x', y') = (y, w - x)  => x = w - y', y = x'
        return np.stack([w - y, x], 1)
    if k == 2:
        return np.stack([w - x, h - y], 1)
    return np.stack([y, h - x], 1)  # k == 3


def extract(
    extractor, image: np.ndarray, side: int | None = None, rot_k: int = 0, mask: np.ndarray | None = None
) -> dict:
    """Features of ``image`` rotated by rot_k*90° CCW and resized to ``side``.

    ``keypoints`` stay in the frame the extractor saw (what matchers with positional encodings expect);
    ``scale``, ``rot_k`` and ``orig_size`` let :func:`to_original` map them back for geometry.
    """
    h, w = image.shape[:2]
    if mask is None:
        mask = valid_mask(image)
    img, m = np.rot90(image, rot_k), np.rot90(mask, rot_k)
    small, s = resize_to_side(np.ascontiguousarray(img), side)
    if s != 1.0:
        m = resize(m.astype(np.uint8), s, nearest=True) > 0
    f = dict(extractor.extract(small, mask=np.ascontiguousarray(m)))
    f["keypoints"] = np.asarray(f["keypoints"], np.float32)
    f["image_size"] = np.array([small.shape[1], small.shape[0]], np.int64)
    f["orig_size"] = np.array([w, h], np.int64)
    f["scale"] = np.float64(s)
    f["rot_k"] = np.int64(rot_k % 4)
    return f


def to_original(f: dict) -> np.ndarray:
    """Keypoints of :func:`extract` in the original image's pixel frame (pixel-edge origin)."""
    w, h = (int(v) for v in f["orig_size"])
    kp = np.asarray(f["keypoints"], np.float64) / float(f["scale"])
    return _rot90_points(kp, int(f["rot_k"]), w, h)


def local_key(db, name: str, conf: dict) -> str:
    """Hash of what the stored tile features depend on: the extractor and its conf, the tiles' working side, the
    tile set and the store's format. Re-ranking settings (thresholds, rotations, geometry) are not part of it, so
    changing them reuses the store."""
    from aeroloc.matching.registry import feature_overrides, reranker_conf

    extractor = reranker_conf(conf["features"], feature_overrides(conf))["extractor"]
    return config_key(
        conf["features"], conf["tile_side"], extractor, db.tiles_hash(), {"feature_format": FEATURE_FORMAT}
    )


def store_for(db, name: str, conf: dict) -> FeatureStore:
    d = Path(db.folder) / "local" / f"{name}-{local_key(db, name, conf)}"
    d.mkdir(parents=True, exist_ok=True)
    return FeatureStore(d / "features.h5")


@dataclass(frozen=True)
class LocalBuildReport:
    """What :func:`build_local` did: the store's file (``path``) and size; ``tiles_per_s`` is 0 on a cache hit."""

    n_tiles: int
    cached: bool
    bytes_per_tile: float
    path: str
    tiles_per_s: float = 0.0


def build_local(db, name: str, device="cpu", conf: dict | None = None, progress: bool = True) -> LocalBuildReport:
    """Precompute the local features of every tile for re-ranker ``name`` (resumable: done tiles are kept)."""
    from tqdm import tqdm

    from aeroloc.matching.registry import build_reranker, feature_overrides, rerank_conf

    rconf = rerank_conf(name, conf)
    store = store_for(db, name, rconf)
    done = store.names()
    todo = [t for t in db.tiles if t.id not in done]
    if not todo:
        return LocalBuildReport(len(db.tiles), cached=True, bytes_per_tile=store.bytes_per_item(), path=str(store.path))
    extractor, _ = build_reranker(rconf["features"], device, feature_overrides(rconf))
    t0 = time.perf_counter()
    batch = {}
    for t in tqdm(todo, desc=f"local features {name}", unit="tile", disable=not progress, leave=False):
        batch[t.id] = extract(extractor, read_image(Path(db.folder) / t.path), rconf["tile_side"])
        if len(batch) >= 32:
            store.write_many(batch)
            batch = {}
    if batch:
        store.write_many(batch)
    dt = time.perf_counter() - t0
    return LocalBuildReport(
        len(db.tiles),
        cached=False,
        bytes_per_tile=store.bytes_per_item(),
        path=str(store.path),
        tiles_per_s=len(todo) / max(dt, 1e-9),
    )
