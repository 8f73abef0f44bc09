"""The code identity that stored results carry (aeroloc.core.provenance): it follows the source of the packages
it covers and nothing else."""

from __future__ import annotations

from aeroloc.core.provenance import LOCALIZATION_PACKAGES, code_identity


def _tree(root, files: dict[str, str]):
    for rel, text in files.items():
        p = root / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(text)
    return root


def test_identity_follows_the_covered_source_only(tmp_path):
    root = _tree(tmp_path / "pkg", {"a/x.py": "A = 1\n", "a/sub/y.py": "B = 2\n", "b/z.py": "C = 3\n"})
    first = code_identity(("a",), root)
    assert len(first) == 12 and first == code_identity(("a",), root)
    # caches, notes and other packages are not the covered source
    _tree(root, {"a/__pycache__/x.cpython-311.pyc": "junk", "a/NOTES.md": "text", "b/z.py": "C = 4\n"})
    code_identity.cache_clear()
    assert code_identity(("a",), root) == first
    assert code_identity(None, root) != code_identity(("b",), root)
    _tree(root, {"a/sub/y.py": "B = 3\n"})  # one byte of a covered file
    code_identity.cache_clear()
    assert code_identity(("a",), root) != first
    changed = code_identity(("a",), root)
    (root / "a/sub/y.py").rename(root / "a/sub/w.py")  # the same bytes under another name
    code_identity.cache_clear()
    assert code_identity(("a",), root) not in (first, changed)


def test_the_installed_package_identity_covers_more_than_localization():
    whole, loc = code_identity(), code_identity(LOCALIZATION_PACKAGES)
    assert whole != loc and len(whole) == len(loc) == 12
