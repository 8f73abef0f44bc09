"""Files that survive a crash, and the keys that name cached work.

Every file aeroloc writes for later reuse (databases, stores, results, downloaded tiles, weights) is written to a
temporary sibling and renamed into place, so an interruption never leaves a half file that looks complete.
"""

from __future__ import annotations

import hashlib
import json
import os
import tempfile
from contextlib import contextmanager
from pathlib import Path


def config_key(*parts) -> str:
    """A short stable hash of JSON-able parts (method conf, weights identity, tile database hash …)."""
    blob = json.dumps(parts, sort_keys=True, default=str).encode()
    return hashlib.sha1(blob).hexdigest()[:12]


def file_identity(path) -> str:
    """Cheap identity of a file for cache keys: size + first/last MiB digest."""
    path = Path(path)
    h = hashlib.sha1(str(path.stat().st_size).encode())
    with open(path, "rb") as f:
        h.update(f.read(1 << 20))
        f.seek(max(0, path.stat().st_size - (1 << 20)))
        h.update(f.read(1 << 20))
    return h.hexdigest()[:16]


@contextmanager
def atomic_path(path: str | os.PathLike):
    """Yields a temporary path beside ``path``; on normal exit it is renamed onto ``path``, on error removed.

    For writers that want a file name (rasterio, h5py, shutil): ``with atomic_path(dest) as tmp: write(tmp)``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix="." + path.name, suffix=".part")
    os.close(fd)
    try:
        yield Path(tmp)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> None:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    atomic_write_bytes(path, text.encode())


def write_json_atomic(path: str | os.PathLike, obj, indent: int | None = 1) -> None:
    atomic_write_text(path, json.dumps(obj, indent=indent, default=str))


def write_csv_atomic(path: str | os.PathLike, fieldnames: list[str], rows) -> None:
    """``rows`` (dicts) under a header of ``fieldnames``, renamed into place when complete."""
    import csv

    with atomic_path(path) as tmp, open(tmp, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=fieldnames)
        w.writeheader()
        w.writerows(rows)
