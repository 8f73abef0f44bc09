"""Which code produced a stored result: a hash of aeroloc's own source.

Results are resumed or reused from disk (a localization's results file, a flight's track, a benchmark's stored
configurations). A result written by other code must be neither: with unchanged settings a changed acceptance
rule had reused old fixes, and a benchmark re-run after a change reported the old code's figures as the new
one's. The identity is a content hash of the package's own source files, so it holds without git (an installed
wheel) and ignores everything outside the package (README, tests, benchmarks).
"""

from __future__ import annotations

import functools
import hashlib
from pathlib import Path

# the subpackages a single-image localization's result depends on
LOCALIZATION_PACKAGES = ("core", "localization", "maps", "matching", "retrieval")


@functools.cache
def code_identity(packages: tuple[str, ...] | None = None, root: Path | None = None) -> str:
    """12 hex digits: SHA-1 over the relative path and bytes of every ``.py`` file of ``packages`` (subpackage
    names, in the order given; None: all) of ``root`` (default: the installed aeroloc package), each package's
    files in path order."""
    root = Path(__file__).resolve().parents[1] if root is None else Path(root)
    groups = [sorted(root.rglob("*.py"))] if packages is None else [sorted((root / p).rglob("*.py")) for p in packages]
    h = hashlib.sha1()
    for files in groups:
        for f in files:
            h.update(f.relative_to(root).as_posix().encode())
            h.update(f.read_bytes())
    return h.hexdigest()[:12]
