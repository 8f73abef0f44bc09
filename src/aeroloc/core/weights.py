"""One place that finds model weights, in this order:

1. an explicit path (``--weights PATH``),
2. ``$AEROLOC_WEIGHTS_DIR/<filename>`` (a folder the user fills by hand, e.g. on an offline machine),
3. the cache ``$AEROLOC_CACHE/weights/<filename>`` (default ``~/.cache/aeroloc/weights``),
4. a file shipped inside an installed Python package,
5. a download from the authors' URL into the cache (atomic: temp file + rename).

When every source fails, :class:`WeightsNotFound` names the URL and the exact path to put the file at.

Checkpoints are read with ``torch.load(weights_only=True)``: tensors, containers and plain values only, never code.
A file that needs pickled Python objects is refused unless it is trusted by name, with ``--trust-checkpoint PATH``
(:func:`trust_checkpoints`) or ``$AEROLOC_TRUST_CHECKPOINTS`` (paths separated by ``os.pathsep``).
"""

from __future__ import annotations

import importlib.util
import os
import pickle
import re
from dataclasses import dataclass
from pathlib import Path

from aeroloc.core.errors import AerolocError, WeightsNotFound
from aeroloc.core.io import atomic_path


@dataclass(frozen=True)
class WeightSource:
    """Where a checkpoint lives.

    filename: the name used in the weights dir and the cache (unique per checkpoint).
    url: the authors' download URL (release asset, Hugging Face ``resolve`` URL, torch.hub URL ...).
    package/package_path: a file shipped inside an installed package (``package`` is the import name).
    """

    filename: str
    url: str | None = None
    package: str | None = None
    package_path: str | None = None
    note: str = ""


def cache_dir() -> Path:
    root = os.environ.get("AEROLOC_CACHE") or os.path.join(
        os.environ.get("XDG_CACHE_HOME", os.path.expanduser("~/.cache")), "aeroloc"
    )
    return Path(root) / "weights"


def _packaged(src: WeightSource) -> Path | None:
    if not src.package:
        return None
    spec = importlib.util.find_spec(src.package)
    if spec is None or not spec.submodule_search_locations:
        return None
    for base in spec.submodule_search_locations:
        p = Path(base) / (src.package_path or src.filename)
        if p.is_file():
            return p
    return None


def _download(url: str, dest: Path) -> None:
    import torch.hub

    with atomic_path(dest) as tmp:
        torch.hub.download_url_to_file(url, str(tmp), progress=os.environ.get("CI") != "true")


def offline() -> bool:
    return os.environ.get("AEROLOC_OFFLINE", "") not in ("", "0") or os.environ.get("HF_HUB_OFFLINE", "") == "1"


def resolve_weights(src: WeightSource, explicit: str | os.PathLike | None = None, download: bool = True) -> Path:
    """Return a local path to the checkpoint described by ``src`` (see the module docstring for the order)."""
    if explicit is not None:
        p = Path(explicit).expanduser()
        if not p.is_file():
            raise WeightsNotFound(f"{p}: weights file not found (given with --weights)")
        return p
    env_dir = os.environ.get("AEROLOC_WEIGHTS_DIR")
    if env_dir and (Path(env_dir) / src.filename).is_file():
        return Path(env_dir) / src.filename
    cached = cache_dir() / src.filename
    if cached.is_file():
        return cached
    packaged = _packaged(src)
    if packaged is not None:
        return packaged
    error = None
    if src.url and download and not offline():
        try:
            _download(src.url, cached)
            return cached
        except Exception as exc:  # network errors come in many types (URLError, HTTPError, OSError ...)
            error = f"{type(exc).__name__}: {exc}"
    where = f"download it from {src.url}" if src.url else "obtain it from the authors"
    hint = f" ({src.note})" if src.note else ""
    why = f" The download failed ({error})." if error else ""
    raise WeightsNotFound(
        f"weights '{src.filename}' not found.{why} {where[0].upper() + where[1:]}{hint} and put it at {cached} "
        f"(or in the folder named by $AEROLOC_WEIGHTS_DIR, or pass --weights PATH)."
    )


TRUST_ENV = "AEROLOC_TRUST_CHECKPOINTS"
_TRUSTED: set[Path] = set()  # --trust-checkpoint paths of this process, resolved


def _resolved(path: str | os.PathLike) -> Path:
    return Path(path).expanduser().resolve()


def trust_checkpoints(paths) -> None:
    """Let :func:`load_checkpoint` unpickle these files (``weights_only=False``) in this process."""
    _TRUSTED.update(_resolved(p) for p in paths or ())


def is_trusted(path: str | os.PathLike) -> bool:
    """Whether ``path`` was trusted by name (:func:`trust_checkpoints` or ``$AEROLOC_TRUST_CHECKPOINTS``)."""
    env = {_resolved(p) for p in os.environ.get(TRUST_ENV, "").split(os.pathsep) if p.strip()}
    return _resolved(path) in _TRUSTED | env


def _torch_load(path, weights_only: bool, mmap: bool):
    import torch

    if mmap:
        try:  # memory-map large zip checkpoints (ViT-G is 4.5 GB) instead of reading them twice
            return torch.load(path, map_location="cpu", weights_only=weights_only, mmap=True)
        except RuntimeError:  # legacy (non-zip) files can't be memory-mapped
            pass
    return torch.load(path, map_location="cpu", weights_only=weights_only)


# what torch's weights-only unpickler says when the file asks for a Python object (not when the file is corrupt)
_NEEDS_OBJECTS = re.compile(r"GLOBAL|Can only create new object|call reduce for unrecognized function")


def load_checkpoint(path: str | os.PathLike, mmap: bool = False):
    """``torch.load`` on the CPU with ``weights_only=True``; a checkpoint that holds pickled Python objects is
    refused with an :class:`AerolocError` naming the file, and loaded in full only when it is trusted by name."""
    try:
        return _torch_load(path, weights_only=True, mmap=mmap)
    except pickle.UnpicklingError as exc:  # torch's weights-only unpickler met something it does not allow
        if not is_trusted(path):
            text = str(exc)
            if not _NEEDS_OBJECTS.search(text):  # a damaged file: torch's own reason, without its advice
                reason = text.split("WeightsUnpickler error:")[-1].split("Check the documentation")[0]
                raise pickle.UnpicklingError(" ".join(reason.split())) from None
            found = re.search(r"GLOBAL (\S+)", text)
            what = f"a pickled {found.group(1)}" if found else "pickled Python objects"
            raise AerolocError(
                f"{path}: checkpoint holds {what}, which loads only by running code from the file; refused. "
                f"If you trust this file, pass --trust-checkpoint {path} "
                f"(or add it to ${TRUST_ENV}, paths separated by '{os.pathsep}')"
            ) from None
    return _torch_load(path, weights_only=False, mmap=mmap)


def load_state_dict(path: Path, key: str | None = None) -> dict:
    """Load a checkpoint on the CPU; ``key`` picks a nested dict (e.g. 'state_dict'); strips 'module.'."""
    try:
        obj = load_checkpoint(path, mmap=True)
    except AerolocError:
        raise
    except Exception as exc:
        raise AerolocError(f"{path}: not a readable PyTorch checkpoint ({type(exc).__name__}: {exc})") from None
    if key is not None and isinstance(obj, dict) and key in obj:
        obj = obj[key]
    if hasattr(obj, "state_dict") and not isinstance(obj, dict):
        obj = obj.state_dict()
    if not isinstance(obj, dict):
        raise AerolocError(f"{path}: checkpoint holds a {type(obj).__name__}, not a state dict")
    return {k[7:] if k.startswith("module.") else k: v for k, v in obj.items()}
