"""The coarse index's graph and codes on 2 MB pages (aeroloc.retrieval.hugepages)."""

from __future__ import annotations

import ctypes
import errno
import mmap
import os
import re
import sys
from pathlib import Path

import numpy as np
import pytest

from aeroloc.retrieval import hugepages
from aeroloc.retrieval.hugepages import HUGE, collapse, collapse_index


def _thp_mode() -> str | None:
    f = Path("/sys/kernel/mm/transparent_hugepage/enabled")
    m = re.search(r"\[(\w+)\]", f.read_text()) if f.is_file() else None
    return m[1] if m else None


def _kernel_at_least(major: int, minor: int) -> bool:
    m = re.match(r"(\d+)\.(\d+)", os.uname().release)
    return m is not None and (int(m[1]), int(m[2])) >= (major, minor)


needs_collapse = pytest.mark.skipif(
    not sys.platform.startswith("linux") or _thp_mode() in (None, "never") or not _kernel_at_least(6, 1),
    reason="MADV_COLLAPSE needs Linux >= 6.1 with transparent huge pages not 'never'",
)


def _anon_huge_kb(start: int, end: int) -> int:
    """AnonHugePages of this process's mappings that overlap ``[start, end)`` (/proc/self/smaps): a buffer from the
    heap can lie over two mappings (seen: 4 MB + 18 MB), so the one holding its second page may hold only part
    of its huge pages (a CI run read 4 MB there while 16 MB were collapsed)."""
    inside, kb = False, 0
    for line in Path("/proc/self/smaps").read_text().splitlines():
        m = re.match(r"^([0-9a-f]+)-([0-9a-f]+) ", line)
        if m:
            inside = int(m[1], 16) < end and start < int(m[2], 16)
        elif inside and line.startswith("AnonHugePages:"):
            kb += int(line.split()[1])
    return kb


def _skip_if_refused_now(got: int, want: int) -> None:
    """Skip, naming the kernel's reason, when fewer bytes than ``want`` were collapsed because the kernel refuses
    a fresh 4 MB buffer in this process too (no free 2 MB page, a momentary lock: not this code's doing);
    a shortfall the kernel does not explain is left to the test's assertions."""
    if got >= want:
        return
    buf = _anonymous(3 * HUGE)
    if collapse(buf.ctypes.data, buf.nbytes) == 0:
        pytest.skip(f"the kernel refuses 2 MB pages now ({errno.errorcode.get(ctypes.get_errno(), '?')})")


def _anonymous(nbytes: int) -> np.ndarray:
    """``nbytes`` of ones in an anonymous private mapping of their own, as the large vectors of an index get
    (glibc maps big allocations): a numpy buffer of this size may instead come from a long-lived worker's heap,
    where a CI run saw the collapse refused for the buffer while a fresh mapping was collapsed."""
    buf = np.frombuffer(mmap.mmap(-1, nbytes, flags=mmap.MAP_PRIVATE | mmap.MAP_ANONYMOUS), np.uint8)
    buf[:] = 1
    return buf


@needs_collapse
def test_collapse_puts_the_whole_huge_pages_of_a_range_on_2mb_pages():
    buf = _anonymous(9 * HUGE)  # 18 MB: at least 8 whole 2 MB pages whatever its alignment
    addr = buf.ctypes.data
    got = collapse(addr, buf.nbytes)
    _skip_if_refused_now(got, 8 * HUGE)
    assert got % HUGE == 0 and 8 * HUGE <= got <= 9 * HUGE, errno.errorcode.get(ctypes.get_errno())
    assert _anon_huge_kb(addr, addr + buf.nbytes) * 1024 >= got  # the kernel reports them as huge pages
    assert (buf == 1).all()  # the same bytes
    assert collapse(addr + 10, HUGE) == 0  # no whole huge page inside: nothing asked, nothing done


@needs_collapse
def test_an_index_on_huge_pages_searches_as_before():
    import faiss

    from aeroloc.retrieval.hugepages import _vectors

    rng = np.random.default_rng(0)
    x = rng.standard_normal((20_000, 256)).astype(np.float32)
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    index = faiss.index_factory(256, "PCA64,L2norm,HNSW32,SQ8", faiss.METRIC_INNER_PRODUCT)
    index.train(x)
    index.add(x)
    kinds = sorted(type(v).__name__ for v in _vectors(index))
    assert kinds == ["MaybeOwnedVectorInt32", "MaybeOwnedVectorUInt8", "UInt64Vector"]  # links, offsets, codes
    before = index.search(x[:50], 10)
    got = collapse_index(index)
    whole = 0  # the whole 2 MB pages inside each vector (the links: 20,000 x 64 x 4 B = 5 MB hold 1 or 2)
    for v in _vectors(index):
        a, n = int(v.data()), v.size() * (8 if "64" in type(v).__name__ else 4 if "32" in type(v).__name__ else 1)
        whole += max(0, (a + n) // HUGE - -(-a // HUGE)) * HUGE
    _skip_if_refused_now(got, whole)
    assert got == whole >= HUGE  # every one of them moved
    after = index.search(x[:50], 10)
    assert np.array_equal(before[1], after[1]) and np.array_equal(before[0], after[0])


def test_collapse_is_a_no_op_where_the_kernel_refuses(monkeypatch):
    """Best effort: a refused madvise (old kernel, no free huge pages) leaves the memory as it was, 0 bytes."""
    monkeypatch.setattr(hugepages, "_madvise", lambda: lambda *a: -1)
    buf = np.ones(3 * HUGE, np.uint8)
    assert collapse(buf.ctypes.data, buf.nbytes) == 0
    monkeypatch.setattr(hugepages, "_madvise", lambda: None)  # not Linux
    assert collapse(buf.ctypes.data, buf.nbytes) == 0
