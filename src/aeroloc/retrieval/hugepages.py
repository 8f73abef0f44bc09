"""Back a loaded index's graph and codes with 2 MB pages (Linux ``madvise(MADV_COLLAPSE)``).

Why: an HNSW walk reads ~1 KB codes at random addresses across the whole index (1.3 GB at 10^6 tiles). With
4 KB pages nearly every read also misses the TLB, and under a hypervisor each miss is a two-level page walk: on
this project's VM, 50,000 random 1 KB reads from 1 GB took 23 ms on 4 KB pages and 15-16 ms on 2 MB pages.
``MADV_COLLAPSE`` (Linux >= 6.1) copies a range into huge pages synchronously and works whatever the system's
transparent-huge-page mode is (``madvise`` or ``always``; not ``never``). It is best effort: where it is not
available, or the kernel finds no free 2 MB pages, the memory stays as it was and nothing else changes (the
same bytes, the same results).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import errno
import re
import sys
import time
from functools import cache

MADV_COLLAPSE = 25
HUGE = 2 << 20
CHUNK = 64 << 20


@cache
def _madvise():
    if not sys.platform.startswith("linux"):
        return None
    libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
    fn = libc.madvise
    fn.argtypes, fn.restype = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int], ctypes.c_int
    return fn


def collapse(address: int, nbytes: int) -> int:
    """Bytes of ``[address, address + nbytes)`` now on huge pages: the whole 2 MB pages inside the range, asked
    for ``CHUNK`` at a time (one call for the 1 GB of codes of a 10^6-tile index was refused as a whole, while
    64 MB calls all succeed: ~3 s per GB; a momentary refusal is asked again); 0 where the kernel refuses or the
    range holds no whole huge page."""
    fn = _madvise()
    start, end = -(-address // HUGE) * HUGE, (address + nbytes) // HUGE * HUGE
    if fn is None:
        return 0
    done = 0
    for a in range(start, end, CHUNK):
        b = min(a + CHUNK, end)
        done += (b - a) if _collapse_chunk(fn, a, b - a) else 0
    return done


def _collapse_chunk(fn, address: int, nbytes: int, tries: int = 3) -> bool:
    """One ``MADV_COLLAPSE`` call, repeated a few milliseconds later while the kernel says the refusal is
    momentary (EAGAIN: a page briefly locked or off the LRU; ENOMEM: no 2 MB page free; EBUSY: the cgroup's
    charge). Two full test-suite runs met refusals (reason not recorded) that the same tests alone never met."""
    for k in range(tries):
        if fn(address, nbytes, MADV_COLLAPSE) == 0:
            return True
        if ctypes.get_errno() not in (errno.EAGAIN, errno.ENOMEM, errno.EBUSY):
            break
        if k + 1 < tries:
            time.sleep(0.005 * (k + 1))
    return False


def _vectors(index) -> list:
    """The faiss vectors a search of ``index`` reads at random: an HNSW graph's links and its storage's codes,
    a flat or scalar-quantizer index's codes; through transforms and refinements."""
    import faiss

    out, todo = [], [index]
    while todo:
        ix = faiss.downcast_index(todo.pop())
        if isinstance(ix, faiss.IndexPreTransform):
            todo.append(ix.index)
        elif isinstance(ix, faiss.IndexRefine):
            todo += [ix.base_index, ix.refine_index]
        elif isinstance(ix, faiss.IndexHNSW):
            out += [ix.hnsw.neighbors, ix.hnsw.offsets]
            todo.append(ix.storage)
        elif hasattr(ix, "codes"):
            out.append(ix.codes)
    return out


def collapse_index(index) -> int:
    """Bytes of ``index``'s graph and codes now on huge pages (see the module docstring)."""
    return sum(collapse(int(v.data()), v.size() * _itemsize(v)) for v in _vectors(index) if v.size())


def _itemsize(vector) -> int:
    """Bytes per element of a faiss SWIG vector, from its type name (``UInt64Vector``, ``MaybeOwnedVectorInt32``,
    ``MaybeOwnedVectorUInt8`` …)."""
    return int(re.search(r"Int(\d+)", type(vector).__name__)[1]) // 8
