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


class ResumableCSV:
    """A results CSV written one row at a time, so an interrupted run resumes where it stopped.

    Rows go to ``OUT.part`` and are flushed as they come; ``OUT.config`` holds the run's ``signature`` (a string
    naming everything the rows depend on). A later run with the same signature keeps the finished rows and
    appends the rest; another signature starts afresh. The final file appears by rename, and ``OUT.done``
    (the signature again) marks it complete, so the same run asked for twice reads it back instead.
    """

    def __init__(self, path: str | os.PathLike, columns: list[str], signature: str):
        self.path, self.columns, self.signature = Path(path), list(columns), signature
        self.part = self.path.with_name(self.path.name + ".part")
        self.sig_path = self.path.with_name(self.path.name + ".config")
        self.done_path = self.path.with_name(self.path.name + ".done")
        self._file = self._writer = None

    def finished(self) -> list[dict] | None:
        """The rows of a complete file written with this signature, else None."""
        if self.path.is_file() and self.done_path.is_file() and self.done_path.read_text() == self.signature:
            return _read_rows(self.path)
        return None

    def start(self) -> list[dict]:
        """Open for appending; returns the rows already finished by an interrupted run of the same signature."""
        import csv

        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.done_path.unlink(missing_ok=True)
        same = self.part.is_file() and self.sig_path.is_file() and self.sig_path.read_text() == self.signature
        rows = _read_rows(self.part) if same else []
        self.sig_path.write_text(self.signature)
        self._file = open(self.part, "a" if rows else "w", newline="")  # noqa: SIM115 (open across write() calls)
        self._writer = csv.DictWriter(self._file, fieldnames=self.columns)
        if not rows:
            self._writer.writeheader()
        return rows

    def write(self, row: dict) -> None:
        self._writer.writerow(row)
        self._file.flush()

    def finish(self) -> None:
        """Rename the finished rows into place and mark them complete."""
        self._file.close()
        os.replace(self.part, self.path)
        self.done_path.write_text(self.signature)
        self.sig_path.unlink(missing_ok=True)

    def close(self) -> None:
        """Stop without finishing (the rows so far stay in ``.part`` for a resume)."""
        if self._file is not None and not self._file.closed:
            self._file.close()


def _read_rows(path: Path) -> list[dict]:
    import csv

    with open(path, newline="") as f:
        return list(csv.DictReader(f))
