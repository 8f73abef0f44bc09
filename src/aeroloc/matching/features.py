"""Local features at a working resolution, with rotations, and the per-database feature store.

Matchers work best when query and tile show the ground at a similar scale, so both are resized so that their
longer side is ``side`` pixels before extraction (NAIP tiles are ~170-260 px at 5 m/px and gain from
upsampling; drone photos are ~3x finer than an orthomosaic and gain from downsampling). Keypoints are kept in the
frame the extractor saw and mapped back (``to_original``) for geometry, so homographies relate original images.
Query rotations (multiples of 90°, and of 90° + 45°) let upright-only matchers handle photos taken at any heading.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from aeroloc.core.frames import DIAGONAL, TILE_TURNS, resize, resize_to_side, rotation_angle, turned, unturn_points
from aeroloc.core.images import valid_mask
from aeroloc.core.io import config_key, write_json_atomic
from aeroloc.matching.store import FEATURE_FORMAT, FeatureStore, ShardedFeatureStore
from aeroloc.retrieval.shards import SHARD_TILES, Shard, ShardJob, mark_complete, write_shard_file


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


def turn_gap(angle_deg: float, rot_k: int) -> float:
    """Degrees (0-180) between a heading-like turn ``angle_deg`` and rotation index ``rot_k``'s."""
    return abs((angle_deg - rotation_angle(rot_k) + 180.0) % 360.0 - 180.0)


def turned_name(tile_id: str, rot_k: int) -> str:
    """The name of a tile's features at rotation index ``rot_k`` in a turned tile store."""
    return f"{tile_id}|{rot_k}"


def turns_within(angle_deg: float, reach_deg: float, diagonals: bool = True) -> list[int]:
    """The rotation indices (quarter turns 0-3, with ``diagonals`` also 4-7) within ``reach_deg`` of
    ``angle_deg``, nearest first (a tie: the quarter turn, the lossless one)."""
    ks = range(2 * DIAGONAL) if diagonals else range(DIAGONAL)
    return sorted(
        (k for k in ks if turn_gap(angle_deg, k) <= reach_deg + 1e-9), key=lambda k: (turn_gap(angle_deg, k), k)
    )


def extract(
    extractor,
    image: np.ndarray,
    side: int | None = None,
    rot_k: int = 0,
    mask: np.ndarray | None = None,
    turn_deg: float = 0.0,
) -> dict:
    """Features of ``image`` turned by :func:`rotation_angle` (``rot_k``) and ``turn_deg`` more, resized to ``side``.

    Rotation indices 0-3 are lossless quarter turns. 4-7 add 45°, and ``turn_deg`` (OpenCV degrees,
    counter-clockwise: a heading prior's own angle) any turn, on a mirrored canvas that holds the whole image
    (aeroloc.core.frames.turned), resized by the factor the quarter turn gets, so the ground keeps the density it
    has against the tiles (the canvas is up to 1.41x longer; shrinking it to ``side`` too made the query 1.3-1.4x
    coarser than the tiles). ``keypoints`` stay in the frame the extractor saw (what matchers with positional
    encodings expect); ``scale``, ``rot_k``, ``orig_size`` (and ``turn_affine``) let :func:`to_original` map
    them back for geometry, so every transform relates the original image whatever the turn.
    """
    h, w = image.shape[:2]
    if mask is None:
        mask = valid_mask(image)
    img, m = np.rot90(image, rot_k % 4), np.rot90(mask, rot_k % 4)
    turn = None
    extra = (45.0 if rot_k % 8 >= DIAGONAL else 0.0) + float(turn_deg)
    if extra % 360.0 != 0.0:
        factor = side / max(img.shape[:2]) if side else 1.0
        img, turned_mask, turn = turned(np.ascontiguousarray(img), extra)
        m = turned_mask & (turned(np.ascontiguousarray(m).astype(np.uint8) * 255, extra, "black")[0] > 0)
        side = round(max(img.shape[:2]) * factor)
    small, s = resize_to_side(np.ascontiguousarray(img), side)
    if s != 1.0:
        m = resize(m.astype(np.uint8), s, nearest=True) > 0
    f = dict(extractor.extract(small, mask=np.ascontiguousarray(m)))
    f["keypoints"] = np.asarray(f["keypoints"], np.float32)
    f["image_size"] = np.array([small.shape[1], small.shape[0]], np.int64)
    f["orig_size"] = np.array([w, h], np.int64)
    f["scale"] = np.float64(s)
    f["rot_k"] = np.int64(rot_k % 8)
    if turn is not None:
        f["turn_affine"] = turn
    return f


def to_original(f: dict) -> np.ndarray:
    """Keypoints of :func:`extract` in the original image's pixel frame (pixel-edge origin)."""
    w, h = (int(v) for v in f["orig_size"])
    kp = np.asarray(f["keypoints"], np.float64) / float(f["scale"])
    if "turn_affine" in f:
        kp = unturn_points(kp, f["turn_affine"])
    return _rot90_points(kp, int(f["rot_k"]) % 4, w, h)


def local_key(db, name: str, conf: dict) -> str:
    """Hash of what the stored tile features depend on: the extractor and its conf, the tiles' working side, the
    tile set and the store's format. Re-ranking settings (thresholds, rotations, geometry) are not part of it, so
    changing them reuses the store."""
    from aeroloc.matching.registry import feature_overrides, reranker_conf

    extractor = reranker_conf(conf["features"], feature_overrides(conf))["extractor"]
    return config_key(
        conf["features"], conf["tile_side"], extractor, db.tiles_hash(), {"feature_format": FEATURE_FORMAT}
    )


def store_for(db, name: str, conf: dict):
    """The re-ranker's tile-feature store: sharded (what builds write), or the single features.h5 of a database
    built before shards existed."""
    d = Path(db.folder) / "local" / f"{name}-{local_key(db, name, conf)}"
    d.mkdir(parents=True, exist_ok=True)
    if (d / "features.h5").is_file() and not (d / "shards").is_dir():
        return FeatureStore(d / "features.h5")
    return ShardedFeatureStore(d, [t.id for t in db.tiles], _shard_size(d))


def turn_store_for(store):
    """The store of the tiles' features at the seven other turns (:data:`TILE_TURNS`, built with
    ``aeroloc build --local-turns``) beside the re-ranker's ``store``, or None when the database has none."""
    if not isinstance(store, ShardedFeatureStore):
        return None
    folder = store.folder / "turns"
    if not (folder / "shards.json").is_file():
        return None
    return ShardedFeatureStore(folder, store.ids, _shard_size(folder))


def _shard_size(folder: Path, default: int = SHARD_TILES) -> int:
    """The shard size a store was built with (``shards.json``), else the default."""
    import json

    try:
        return int(json.loads((folder / "shards.json").read_text())["shard_tiles"])
    except (OSError, ValueError, KeyError):
        return default


@dataclass(frozen=True)
class LocalTask:
    """Extract a shard's tile features with re-ranker ``name`` into ``folder/shards/NNNNN.h5`` (a
    :class:`~aeroloc.retrieval.shards.ShardTask`)."""

    name: str
    rconf: dict
    folder: Path
    turns: bool = False  # the tiles at :data:`TILE_TURNS` (names :func:`turned_name`) instead of upright

    def open(self):
        from aeroloc.matching.registry import build_reranker, feature_overrides

        extractor, _ = build_reranker(self.rconf["features"], "cpu", feature_overrides(self.rconf))
        return extractor

    def run(self, extractor, shard: Shard, images: list[np.ndarray], ids: list[str]) -> None:
        side = self.rconf["tile_side"]
        if self.turns:
            feats = {
                turned_name(t, k): extract(extractor, im, side, k) for t, im in zip(ids, images) for k in TILE_TURNS
            }
        else:
            feats = {t: extract(extractor, im, side) for t, im in zip(ids, images)}
        path = self.folder / "shards" / f"{shard.name}.h5"
        path.parent.mkdir(parents=True, exist_ok=True)
        write_shard_file(path, lambda tmp: _write_h5(tmp, feats))
        mark_complete(self.folder, shard)


def _write_h5(tmp: Path, feats: dict) -> None:
    tmp.unlink(missing_ok=True)  # h5py creates the file itself
    FeatureStore(tmp).write_many(feats)


@dataclass(frozen=True)
class LocalBuildReport:
    """What :func:`build_local` did: the store's folder (``path``) and size; ``tiles_per_s`` is 0 on a cache hit."""

    n_tiles: int
    cached: bool
    bytes_per_tile: float
    path: str
    tiles_per_s: float = 0.0


def build_local(
    db,
    name: str,
    device="cpu",
    conf: dict | None = None,
    progress: bool = True,
    ray: str | None = None,
    workers: int | None = None,
    shard_size: int = SHARD_TILES,
    turns: bool = False,
) -> LocalBuildReport:
    """Precompute the local features of every tile for re-ranker ``name``, shard by shard (resumable: finished
    shards are kept), in this process or on the Ray cluster at ``ray``; the same shard code either way. With
    ``turns`` also every tile at the seven other turns (:func:`turn_store_for`): a photo of unknown heading is
    then extracted once and screened against turned tiles, instead of extracted at up to eight turns (the bytes
    and the build time of the local features x8). The report is the upright store's; ``tiles_per_s`` counts both."""
    from aeroloc.matching.registry import rerank_conf

    rconf = rerank_conf(name, conf)
    store = store_for(db, name, rconf)
    folder = store.path.parent if isinstance(store, FeatureStore) else store.folder
    n_new = dt = 0.0
    cached = len(store.names()) >= len(db.tiles)
    if not cached:  # an old unfinished store is continued as shards of the size it was started with
        n_new, dt = _build_shards(
            db, LocalTask(name, rconf, folder), shard_size, f"local features {name}", progress, ray, workers
        )
    if turns:
        turn_folder = folder / "turns"
        have = turn_store_for(ShardedFeatureStore(folder, [t.id for t in db.tiles], _shard_size(folder)))
        if have is None or len(have.names()) < len(db.tiles):
            task = LocalTask(name, rconf, turn_folder, turns=True)
            n_turned, dt_turned = _build_shards(db, task, shard_size, f"turned tiles {name}", progress, ray, workers)
            n_new, dt, cached = max(n_new, n_turned), dt + dt_turned, False
    store = store_for(db, name, rconf)
    return LocalBuildReport(
        len(db.tiles),
        cached=cached,
        bytes_per_tile=store.bytes_per_item(),
        path=str(store.path),
        tiles_per_s=n_new / max(dt, 1e-9) if not cached else 0.0,
    )


def _build_shards(db, task: LocalTask, shard_size: int, label: str, progress, ray, workers) -> tuple[int, float]:
    """Run ``task`` over the tiles' shards into ``task.folder`` (its shard size kept once started); returns
    (tiles extracted, seconds)."""
    from aeroloc.retrieval.database import run_shards

    task.folder.mkdir(parents=True, exist_ok=True)
    shard_size = _shard_size(task.folder, shard_size)
    write_json_atomic(task.folder / "shards.json", {"shard_tiles": shard_size})
    return run_shards(db, ShardJob(str(db.folder), task, shard_size), label, progress, ray, workers)
