"""A retrieval database folder: tiles (``tiles.csv``, ``images/``) + per-method global descriptors and Faiss
index + per-reranker local features. Each part is cached under a key that hashes its configuration.

Layout::

    DB/tiles.csv, tiles.json [, images/]     (aeroloc.maps.tiling; pixels: aeroloc.maps.tilesource)
    DB/global/<method>-<key>/                model.pt (fitted state), shards/NNNNN.npy + .done (the build's
                                             shards, aeroloc.retrieval.shards), descriptors.npy, meta.json,
                                             index.faiss [+ index.faiss.ivfdata]
    DB/global/<method>-<key>/turns/          the same for every tile at the seven other turns (--global-turns)
    DB/local/<reranker>-<key>/shards/NNNNN.h5 + .done   (aeroloc.matching.store; features.h5 in old databases)
    DB/db.json                               which method/reranker folders exist, the default method
"""

from __future__ import annotations

import dataclasses
import io
import json
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from aeroloc.core.errors import AerolocError
from aeroloc.core.io import atomic_write_bytes, config_key, file_identity, write_json_atomic
from aeroloc.maps import tiling
from aeroloc.retrieval.shards import SHARD_TILES, TORCH_THREADS, torch_threads
from aeroloc.retrieval.store import DescriptorStore

DB_JSON = "db.json"
TURNS_DIR = "turns"  # a method's turned descriptors, beside its upright ones


def _progress(total, desc, enabled, initial=0):
    from tqdm import tqdm

    return tqdm(
        total=total, initial=initial, desc=desc, unit="tile", disable=not enabled, leave=False, dynamic_ncols=True
    )


class Database:
    def __init__(self, folder):
        self.folder = Path(folder)
        self.tiles = tiling.load_tiles(self.folder)
        self.info = tiling.load_info(self.folder)
        self.by_id = {t.id: t for t in self.tiles}
        p = self.folder / DB_JSON
        self.meta = json.loads(p.read_text()) if p.is_file() else {"global": {}, "local": {}}
        self.position = {t.id: i for i, t in enumerate(self.tiles)}
        self._source = None

    def tiles_hash(self) -> str:
        return file_identity(self.folder / tiling.TILES_CSV)

    def tile_paths(self) -> list[Path]:
        return [self.folder / t.path for t in self.tiles]

    @property
    def source(self):
        """The tiles' pixels (:class:`aeroloc.maps.tilesource.TileSource`): images/ if written, else the map."""
        if self._source is None:
            from aeroloc.maps.tilesource import TileSource

            self._source = TileSource(self.folder, self.tiles, self.info)
        return self._source

    def tile_image(self, tile_id: str) -> np.ndarray:
        """RGB uint8 of a tile: its window of the map (refused if the map changed), or its PNG when written."""
        return self.source.image(self.position[tile_id])

    def tile_images(self, start: int, stop: int):
        """Tiles ``start`` .. ``stop`` - 1 (tiles.csv order), read in band windows of the map."""
        return self.source.images(start, stop)

    def save_meta(self) -> None:
        write_json_atomic(self.folder / DB_JSON, self.meta)

    # --- global descriptors ---------------------------------------------------------------------------
    def global_dir(self, method: str | None = None) -> tuple[str, Path]:
        entries = self.meta.get("global", {})
        method = method or self.meta.get("default_method")
        if not method or method not in entries:
            have = ", ".join(sorted(entries)) or "none"
            raise AerolocError(
                f"{self.folder}: no descriptors for method '{method}' (built: {have}); "
                "run 'aeroloc build' with --method"
            )
        return method, self.folder / entries[method]["dir"]

    def load_method(self, method: str | None = None, device="cpu"):
        """(model, store, index, conf) of a built method, ready for queries."""
        from aeroloc.retrieval.models import build_method

        method, gdir = self.global_dir(method)
        entry = self.meta["global"][method]
        store, index = self.load_search(method)
        model = build_method(method, entry.get("conf"), entry.get("weights"), device="cpu")
        if (gdir / "model.pt").is_file():
            model.load_state_dict(_load_fitted(gdir / "model.pt"), strict=True)
        model = model.to(device).eval()
        return model, store, index, entry

    def load_search(self, method: str | None = None):
        """(store, index) of a built method: what searching the stored descriptors needs, without the model."""
        from aeroloc.retrieval.index import load_index

        _, gdir = self.global_dir(method)
        return DescriptorStore.open_complete(gdir), load_index(gdir / "index.faiss")

    def load_turned(self, method: str | None = None):
        """The Faiss index of the tiles at the seven other turns (``aeroloc build --global-turns``; row ``i * 7 +
        k - 1`` is tile i at rotation index k), or None when the method has none (or it is unfinished)."""
        from aeroloc.retrieval.index import load_index

        _, gdir = self.global_dir(method)
        folder = gdir / TURNS_DIR
        return load_index(folder / "index.faiss") if _turned_rows(folder) is not None else None


def _turned_rows(folder: Path) -> int | None:
    """The rows of a turned descriptor folder whose store and index are both finished, else None."""
    if not (folder / "index.faiss").is_file():
        return None
    try:
        return DescriptorStore.open_complete(folder).n
    except AerolocError:
        return None


@dataclass(frozen=True)
class GlobalBuildReport:
    """What :func:`build_global` did for one method.

    ``dir`` is the method's folder relative to the database; sizes are bytes. The seconds are those of this call:
    all 0 on a cache hit (``cached``), and ``fit_s`` is 0 when a fitted vocabulary was reused.
    """

    method: str
    key: str
    dir: str
    n_tiles: int
    dim: int
    bytes_per_tile: float
    index_bytes: int
    cached: bool
    fit_s: float = 0.0
    extract_s: float = 0.0
    index_s: float = 0.0
    total_s: float = 0.0
    tiles_per_s: float = 0.0
    turned_rows: int = 0  # rows of the turned descriptors (tiles x 7, ``turns``), 0 without them


def build_global(
    db: Database,
    method: str,
    conf: dict | None = None,
    weights=None,
    device="cpu",
    batch_size: int = 16,
    workers: int | None = None,
    index_factory: str = "auto",
    half: bool = False,
    fit_max_tiles: int = 2000,
    progress: bool = True,
    ray: str | None = None,
    shard_size: int = SHARD_TILES,
    turns: bool = False,
) -> GlobalBuildReport:
    """Descriptors of every tile + a Faiss index, cached and resumable per shard. Returns timings and sizes.

    The shards run in this process, or on the Ray cluster at ``ray`` (``"local"``: a new local one) with
    ``workers`` model actors; both run the same shard code on CPU, so the results are identical. ``device`` and
    ``half`` are kept for the API; the shard build describes on CPU (batches of ``batch_size``). ``turns``: every
    tile also described at the seven other turns, with its own index (:meth:`Database.load_turned`; 8x the
    descriptors and their time), so that a photo of unknown heading retrieves its place with one descriptor."""
    from aeroloc.retrieval.global_shards import TurnedGlobalTask

    conf = dict(conf or {})
    args = (batch_size, workers, index_factory, fit_max_tiles, progress, ray, shard_size)
    report = _build_upright(db, method, conf, weights, *args)
    if turns:
        folder = db.folder / report.dir / TURNS_DIR
        task = TurnedGlobalTask(method, conf, str(weights) if weights else None, folder, batch_size)
        rows = _build_turned(db, task, report.dim, index_factory, progress, ray, workers, shard_size)
        report = dataclasses.replace(report, turned_rows=rows)
    return report


def _build_upright(
    db: Database,
    method: str,
    conf: dict,
    weights,
    batch_size,
    workers,
    index_factory,
    fit_max_tiles,
    progress,
    ray,
    shard_size,
) -> GlobalBuildReport:
    """The upright descriptors and index of :func:`build_global` (cached, or built)."""
    from aeroloc.retrieval.global_shards import GlobalTask
    from aeroloc.retrieval.models import build_method
    from aeroloc.retrieval.shards import ShardJob

    key, gdir, entry = _global_entry(db, method, conf, weights, index_factory)
    cached = _cached_build(db, method, key, gdir, entry)
    if cached is not None:
        return cached
    t_start = time.perf_counter()
    model = build_method(method, conf, weights, device="cpu")
    model, t_fit = _fit_vocabulary(model, gdir / "model.pt", db, fit_max_tiles)
    task = GlobalTask(method, conf, str(weights) if weights else None, gdir, batch_size)
    job = ShardJob(str(db.folder), task, shard_size)
    n_new, t_desc = run_shards(db, job, f"descriptors {method}", progress, ray, workers)
    store = _merge_store(db, gdir, job, model.dim, {"method": method, "conf": conf, "key": key}, t_desc, t_fit)
    t_index, used = _build_index(store, gdir / "index.faiss", index_factory)
    _register(db, method, {**entry, "index_used": used})
    return _report(
        db,
        method,
        key,
        entry,
        store,
        cached=False,
        fit_s=t_fit,
        extract_s=t_desc,
        index_s=t_index,
        total_s=time.perf_counter() - t_start,
        tiles_per_s=n_new / max(t_desc, 1e-9),
    )


def run_shards(db: Database, job, desc: str, progress: bool, ray: str | None, workers: int | None):
    """Build the job's unfinished shards (in-process, or on Ray at ``ray``); (tiles built, seconds)."""
    from aeroloc.retrieval.shards import run_in_process

    todo = job.todo(len(db.tiles))
    n_todo = sum(len(s) for s in todo)
    bar = _progress(len(db.tiles), desc, progress, initial=len(db.tiles) - n_todo)
    t0 = time.perf_counter()
    if ray is not None:
        from aeroloc.retrieval.ray_build import run_on_ray

        run_on_ray(job, todo, ray, workers, progress=bar.update)
    else:
        run_in_process(job, todo, progress=bar.update)
    bar.close()
    return n_todo, time.perf_counter() - t0


def _build_turned(
    db: Database, task, dim: int, index_factory: str, progress: bool, ray, workers, shard_size: int
) -> int:
    """The turned descriptors (``task``, a TurnedGlobalTask whose folder is the method's ``turns/``; ``dim``
    the upright ones') and their index, unless complete: the same shards, resume and Ray path as the upright
    build, the same vocabulary. Returns their rows."""
    from aeroloc.core.frames import TILE_TURNS
    from aeroloc.retrieval.shards import ShardJob

    rows = _turned_rows(task.folder)
    if rows is not None:
        return rows
    job = ShardJob(str(db.folder), task, shard_size)
    _, t_desc = run_shards(db, job, f"turned descriptors {task.method}", progress, ray, workers)
    meta = {"method": task.method, "turns": list(TILE_TURNS), "tiles": len(db.tiles)}
    store = _merge_store(db, task.folder, job, dim, meta, t_desc, 0.0, rows_per_tile=len(TILE_TURNS))
    _build_index(store, task.folder / "index.faiss", index_factory)
    return store.n


def _merge_store(
    db: Database, gdir: Path, job, dim: int, meta: dict, t_desc: float, t_fit: float, rows_per_tile: int = 1
):
    """The complete shards concatenated into the method's DescriptorStore, marked complete."""
    from aeroloc.retrieval.global_shards import merge

    n = len(db.tiles) * rows_per_tile
    merge(gdir, job.shards(len(db.tiles)), n, dim, rows_per_tile)
    store = DescriptorStore(gdir, n, dim, meta)
    store.meta = {**meta, "extract_s": t_desc, "fit_s": t_fit, "n": store.n, "dim": dim, "dtype": "float16"}
    store.meta["complete"] = True
    write_json_atomic(gdir / "meta.json", store.meta)
    return store


def _global_entry(db: Database, method: str, conf: dict, weights, index_factory: str) -> tuple[str, Path, dict]:
    """The method's cache key, its folder, and its db.json entry."""
    from aeroloc.retrieval.models import method_class

    weights_id = file_identity(weights) if weights else None
    # the key covers the method's full effective configuration (class defaults included), so a changed
    # default never reuses a stale vocabulary or descriptors
    full_conf = {**getattr(method_class(method), "default_conf", {}), **conf}
    key = config_key(method, full_conf, weights_id, db.tiles_hash(), index_factory)
    gdir = db.folder / "global" / f"{method}-{key}"
    # the full effective configuration, so queries are described exactly as the tiles were even after a class
    # default changes (an entry with the overrides only would pick up the new default for queries alone)
    entry = {
        "dir": str(gdir.relative_to(db.folder)),
        "conf": _jsonable(full_conf),
        "weights": str(weights) if weights else None,
        "index": index_factory,
    }
    return key, gdir, entry


def _register(db: Database, method: str, entry: dict) -> None:
    """Record the method in db.json and make it the default."""
    db.meta.setdefault("global", {})[method] = entry
    db.meta["default_method"] = method
    db.save_meta()


def _cached_build(db: Database, method: str, key: str, gdir: Path, entry: dict) -> GlobalBuildReport | None:
    """The report of a complete earlier build in ``gdir`` (registered again), or None when there is none."""
    if not ((gdir / "meta.json").is_file() and (gdir / "index.faiss").is_file()):
        return None
    existing = DescriptorStore.open_complete(gdir)
    # the index the build chose is part of the entry: a cached build keeps it (results signatures read the entry)
    used = db.meta.get("global", {}).get(method, {}).get("index_used")
    _register(db, method, {**entry, **({"index_used": used} if used else {})})
    return _report(db, method, key, entry, existing, cached=True)


def _report(db: Database, method: str, key: str, entry: dict, store: DescriptorStore, **times) -> GlobalBuildReport:
    """The report of a build whose descriptors are in ``store`` (``times``: cached and the stage seconds)."""
    return GlobalBuildReport(
        method=method,
        key=key,
        dir=entry["dir"],
        n_tiles=len(db.tiles),
        dim=store.dim,
        bytes_per_tile=store.bytes_per_item(),
        index_bytes=(store.folder / "index.faiss").stat().st_size,
        **times,
    )


def _load_fitted(path: Path) -> dict:
    """A method's fitted state (``model.pt``, a plain state dict of tensors), read with ``weights_only=True``."""
    import torch

    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:
        raise AerolocError(
            f"{path}: not a readable fitted state ({type(exc).__name__}: {exc}); delete {path.parent} to rebuild it"
        ) from None


def _fit_vocabulary(model, state_path: Path, db: Database, fit_max_tiles: int):
    """(model, seconds): a model that needs fitting gets the saved state, or is fitted once, here, on up to
    ``fit_max_tiles`` tiles (a fixed random sample, read as windows) and its state saved for every shard worker;
    other models are returned as they are."""
    import torch

    if not getattr(model, "needs_fit", False):
        return model, 0.0
    if state_path.is_file():
        model.load_state_dict(_load_fitted(state_path), strict=True)
        return model, 0.0
    t0 = time.perf_counter()
    rng = np.random.default_rng(0)
    n = len(db.tiles)
    pick = sorted(rng.choice(n, min(n, fit_max_tiles), replace=False))
    # at the shard workers' torch threads: the dense descriptors differ in the last bits with the thread count and
    # k-means amplifies that (levir-tx at 2 threads vs 1: centroids 0.02 apart, a query's true tile retrieved at
    # rank 16 in one build and not in the top 20 in the other), so the vocabulary would depend on the machine
    with torch_threads(TORCH_THREADS):
        model.fit(db.source.image(int(i)) for i in pick)
    state_path.parent.mkdir(parents=True, exist_ok=True)
    buf = io.BytesIO()  # torch names the archive after the file: a buffer keeps the bytes the same every build
    torch.save({k: v.cpu() for k, v in model.state_dict().items()}, buf)
    atomic_write_bytes(state_path, buf.getvalue())
    return model, time.perf_counter() - t0


def _build_index(store: DescriptorStore, path: Path, index_factory: str) -> tuple[float, str]:
    """Build and save the Faiss index over the complete store, chunk by chunk; (seconds, factory used)."""
    from aeroloc.retrieval.index import build_index_from_store

    t0 = time.perf_counter()
    used = build_index_from_store(store.path, path, index_factory)
    return time.perf_counter() - t0, used


def _jsonable(conf: dict) -> dict:
    """The configuration as db.json will hold it (tuples become lists; the models accept both)."""
    return json.loads(json.dumps(conf))
