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
        import torch

        from aeroloc.retrieval.index import load_index
        from aeroloc.retrieval.models import build_method

        method, gdir = self.global_dir(method)
        entry = self.meta["global"][method]
        store = DescriptorStore.open_complete(gdir)
        model = build_method(method, entry.get("conf"), entry.get("weights"), device="cpu")
        if (gdir / "model.pt").is_file():
            model.load_state_dict(torch.load(gdir / "model.pt", map_location="cpu"), strict=True)
        model = model.to(device).eval()
        return model, store, load_index(gdir / "index.faiss"), entry


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
) -> dict:
    """Descriptors of every tile + a Faiss index, cached and resumable. Returns timings and sizes."""
    import torch

    from aeroloc.core.images import read_image
    from aeroloc.retrieval.descriptors import iter_descriptors
    from aeroloc.retrieval.index import build_index, save_index
    from aeroloc.retrieval.models import build_method, method_class

    conf = dict(conf or {})
    weights_id = file_identity(weights) if weights else None
    # the key covers the method's full effective configuration (class defaults included), so a changed
    # default never reuses a stale vocabulary or descriptors
    full_conf = {**getattr(method_class(method), "default_conf", {}), **conf}
    key = config_key(method, full_conf, weights_id, db.tiles_hash(), index_factory)
    gdir = db.folder / "global" / f"{method}-{key}"
    report = {"method": method, "key": key, "dir": str(gdir.relative_to(db.folder)), "n_tiles": len(db.tiles)}
    # the full effective configuration, so queries are described exactly as the tiles were even after a class
    # default changes (an entry with the overrides only would pick up the new default for queries alone)
    entry = {
        "dir": report["dir"],
        "conf": _jsonable(full_conf),
        "weights": str(weights) if weights else None,
        "index": index_factory,
    }
    if (gdir / "meta.json").is_file() and (gdir / "index.faiss").is_file():
        existing = DescriptorStore.open_complete(gdir)
        db.meta.setdefault("global", {})[method] = entry
        db.meta["default_method"] = method
        db.save_meta()
        return {**report, "cached": True, "dim": existing.dim, "bytes_per_tile": existing.bytes_per_item()}
    t_start = time.perf_counter()
    model = build_method(method, conf, weights, device="cpu")
    dev = torch.device(device) if isinstance(device, str) else device
    paths = db.tile_paths()
    t_fit = 0.0
    if getattr(model, "needs_fit", False):
        state_path = gdir / "model.pt"
        if state_path.is_file():
            model.load_state_dict(torch.load(state_path, map_location="cpu"), strict=True)
        else:
            t0 = time.perf_counter()
            rng = np.random.default_rng(0)
            pick = sorted(rng.choice(len(paths), min(len(paths), fit_max_tiles), replace=False))
            model = model.to(dev)
            model.fit(read_image(paths[i]) for i in pick)
            gdir.mkdir(parents=True, exist_ok=True)
            with atomic_path(state_path) as tmp:
                torch.save({k: v.cpu() for k, v in model.state_dict().items()}, tmp)
            t_fit = time.perf_counter() - t0
    model = model.to(dev).eval()
    store = DescriptorStore(gdir, len(paths), model.dim, {"method": method, "conf": conf, "key": key})
    start, write, finish = store.writer()
    t0 = time.perf_counter()
    bar = _progress(len(paths), f"descriptors {method}", progress, initial=start)
    for batch in iter_descriptors(model, paths[start:], dev, batch_size, workers, half):
        write(batch)
        bar.update(len(batch))
    bar.close()
    t_desc = time.perf_counter() - t0
    finish({"extract_s": t_desc, "fit_s": t_fit})
    t0 = time.perf_counter()
    index = build_index(store.load(mmap=False).astype(np.float32), index_factory)
    save_index(index, gdir / "index.faiss")
    t_index = time.perf_counter() - t0
    db.meta.setdefault("global", {})[method] = entry
    db.meta["default_method"] = method
    db.save_meta()
    return {
        **report,
        "cached": False,
        "dim": model.dim,
        "fit_s": t_fit,
        "extract_s": t_desc,
        "index_s": t_index,
        "total_s": time.perf_counter() - t_start,
        "tiles_per_s": (len(paths) - start) / max(t_desc, 1e-9),
        "bytes_per_tile": store.bytes_per_item(),
        "index_bytes": (gdir / "index.faiss").stat().st_size,
    }


def _jsonable(conf: dict) -> dict:
    """The configuration as db.json will hold it (tuples become lists; the models accept both)."""
    return json.loads(json.dumps(conf))
