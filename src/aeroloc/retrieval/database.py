"""A retrieval database folder: tiles (``tiles.csv``, ``images/``) + per-method global descriptors and Faiss
index + per-reranker local features. Each part is cached under a key that hashes its configuration.

Layout::

    DB/tiles.csv, tiles.json, images/        (aeroloc.maps.tiling)
    DB/global/<method>-<key>/                model.pt (fitted state), descriptors.npy, meta.json, index.faiss
    DB/local/<reranker>-<key>/features.h5    (aeroloc.matching.store.FeatureStore)
    DB/db.json                               which method/reranker folders exist, the default method
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from aeroloc.core.errors import AerolocError
from aeroloc.core.io import atomic_path, config_key, file_identity, write_json_atomic
from aeroloc.maps import tiling
from aeroloc.retrieval.store import DescriptorStore

DB_JSON = "db.json"


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

    def tiles_hash(self) -> str:
        return file_identity(self.folder / tiling.TILES_CSV)

    def tile_paths(self) -> list[Path]:
        return [self.folder / t.path for t in self.tiles]

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
        from aeroloc.retrieval.index import load_index
        from aeroloc.retrieval.models import build_method

        method, gdir = self.global_dir(method)
        entry = self.meta["global"][method]
        store = DescriptorStore.open_complete(gdir)
        model = build_method(method, entry.get("conf"), entry.get("weights"), device="cpu")
        if (gdir / "model.pt").is_file():
            model.load_state_dict(_load_fitted(gdir / "model.pt"), strict=True)
        model = model.to(device).eval()
        return model, store, load_index(gdir / "index.faiss"), entry


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


def build_global(
    db: Database,
    method: str,
    conf: dict | None = None,
    weights=None,
    device="cpu",
    batch_size: int = 16,
    workers: int | None = None,
    index_factory: str = "Flat",
    half: bool = False,
    fit_max_tiles: int = 2000,
    progress: bool = True,
) -> GlobalBuildReport:
    """Descriptors of every tile + a Faiss index, cached and resumable. Returns timings and sizes."""
    import torch

    from aeroloc.retrieval.models import build_method

    conf = dict(conf or {})
    key, gdir, entry = _global_entry(db, method, conf, weights, index_factory)
    cached = _cached_build(db, method, key, gdir, entry)
    if cached is not None:
        return cached
    t_start = time.perf_counter()
    model = build_method(method, conf, weights, device="cpu")
    dev = torch.device(device) if isinstance(device, str) else device
    paths = db.tile_paths()
    model, t_fit = _fit_vocabulary(model, gdir / "model.pt", paths, dev, fit_max_tiles)
    model = model.to(dev).eval()
    store = DescriptorStore(gdir, len(paths), model.dim, {"method": method, "conf": conf, "key": key})
    n_new, t_desc = _fill_store(
        store, model, paths, dev, batch_size, workers, half, f"descriptors {method}", progress, fit_s=t_fit
    )
    t_index = _build_index(store, gdir / "index.faiss", index_factory)
    _register(db, method, entry)
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
    _register(db, method, entry)
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


def _fit_vocabulary(model, state_path: Path, paths: list[Path], dev, fit_max_tiles: int):
    """(model, seconds): a model that needs fitting gets the saved state, or is fitted on up to ``fit_max_tiles``
    tiles (a fixed random sample) and its state saved; other models are returned as they are."""
    import torch

    from aeroloc.core.images import read_image

    if not getattr(model, "needs_fit", False):
        return model, 0.0
    if state_path.is_file():
        model.load_state_dict(_load_fitted(state_path), strict=True)
        return model, 0.0
    t0 = time.perf_counter()
    rng = np.random.default_rng(0)
    pick = sorted(rng.choice(len(paths), min(len(paths), fit_max_tiles), replace=False))
    model = model.to(dev)
    model.fit(read_image(paths[i]) for i in pick)
    state_path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(state_path) as tmp:
        torch.save({k: v.cpu() for k, v in model.state_dict().items()}, tmp)
    return model, time.perf_counter() - t0


def _fill_store(
    store: DescriptorStore, model, paths, dev, batch_size, workers, half, desc: str, progress: bool, fit_s: float
) -> tuple[int, float]:
    """Describe the tiles the store lacks (resuming after its last flushed row) and mark it complete.
    Returns (tiles described, seconds)."""
    from aeroloc.retrieval.descriptors import iter_descriptors

    start, write, finish = store.writer()
    t0 = time.perf_counter()
    bar = _progress(len(paths), desc, progress, initial=start)
    for batch in iter_descriptors(model, paths[start:], dev, batch_size, workers, half):
        write(batch)
        bar.update(len(batch))
    bar.close()
    t_desc = time.perf_counter() - t0
    finish({"extract_s": t_desc, "fit_s": fit_s})
    return len(paths) - start, t_desc


def _build_index(store: DescriptorStore, path: Path, index_factory: str) -> float:
    """Build and save the Faiss index over the complete store; returns the seconds it took."""
    from aeroloc.retrieval.index import build_index, save_index

    t0 = time.perf_counter()
    index = build_index(store.load(mmap=False).astype(np.float32), index_factory)
    save_index(index, path)
    return time.perf_counter() - t0


def _jsonable(conf: dict) -> dict:
    """The configuration as db.json will hold it (tuples become lists; the models accept both)."""
    return json.loads(json.dumps(conf))
