"""Keep freed memory inside the process during a CPU forward (glibc malloc settings).

Why: a VGGT forward allocates and frees large activations hundreds of times (MLP hidden
states, attention score blocks, the DPT heads' full-resolution maps). glibc serves every
allocation above its mmap threshold (at most 32 MB, 128 kB at start) with a fresh ``mmap``
and returns it with ``munmap`` on free, so the kernel faults in and zeroes new pages for each
one. Measured on the 2-core development VM (2 threads, 518 px, random weights): 6 frames fp32
spent 16-18 s of its 210 CPU s in the kernel (0.6 M page faults); 12 frames fp32 190 s of
736 CPU s (29 M faults). On that VM a page the process has never touched costs about 2.7 CPU s
per GB, because the hypervisor backs it only on first touch.

:func:`retain_freed_memory` raises glibc's mmap and trim thresholds to 2 GB, so the trunk's
activations and the heads' maps (a 4-frame chunk's full-resolution [4, 128, 518, 518] float32
map is 549 MB) come from the heap, and freed blocks are reused by the next layer without a
fault. The cost is fragmentation: the heap's high-water mark exceeds the live peak,
which :func:`release_free_memory` (``malloc_trim``) limits by returning whole free pages to
the system, e.g. after the model weights were converted. 6 frames, one run each (fp32 / bf16):
glibc defaults 109 / 56-68 s, 6.3 / 4.7 GB peak RSS; 2 GB thresholds 91 / 46 s, 7.4 / 5.8 GB;
512 MB mmap threshold 97 / 56 s, 7.5 / 5.7 GB (the largest maps mapped anew each chunk).

Reuse relies on torch's 2 MB-aligned large allocations (``THP_MEM_ALLOC_ENABLE=1``, which
``vggt_init`` sets): with 64-byte alignment glibc's memalign needs a few bytes more than a
freed block of the same size offers, so a block freed in the middle of the heap is not
reused for the same request (seen with ``THP_MEM_ALLOC_ENABLE=0``: a 64 MB buffer allocated
and freed in a loop moved up the heap each round). tests/test_runtime_memory.py runs with huge
pages on.

Reuse is not guaranteed even then, so the tests assert only what the settings control (heap,
not mmap; kept, not unmapped). glibc serves a small request made between the free and the
next large request from the start of the freed large chunk (splitting it), after which the
chunk is a few bytes short of the large request and the heap grows instead. A C probe with
the same settings: malloc(64 MB), a 100-byte guard, then per round free + malloc(64 MB): the
same address every round; with a malloc(200) between the free and the malloc(64 MB): the
200 bytes land at the old block's address and the 64 MB block moves to a new 64 MB of heap
(once in that probe; every round in a CI run whose other threads allocated in between). The
memory stays in the process either way (no unmap, no trim); what the growth costs is first
touches of the new pages, which ``benchmarks/bench_vggt.py --reuse-probe`` measures.

Only glibc (Linux) is affected; elsewhere both functions do nothing and return False. The
settings are process-wide: the ``vggt_init`` and ``splat_train`` CLIs apply them, library users
opt in. ``RETAIN_FREED_MEMORY=0`` (environment, :data:`ENV`) turns :func:`retain_freed_memory`
off; the former name ``VGGT_INIT_RETAIN_MEMORY`` still works, with a deprecation warning.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import os
import sys

__all__ = ["ENV", "retain_freed_memory", "release_free_memory", "memory_retained", "heap_stats"]

ENV = "RETAIN_FREED_MEMORY"  # "0" turns retain_freed_memory off
_OLD_ENV = "VGGT_INIT_RETAIN_MEMORY"  # the former name, read when ENV is unset

log = logging.getLogger(__name__)

_M_TRIM_THRESHOLD = -1  # glibc <malloc.h>
_M_MMAP_THRESHOLD = -3
MMAP_THRESHOLD = 2**31 - 1  # allocations below this (2 GB; mallopt takes an int) come from the heap
TRIM_THRESHOLD = 2**31 - 1  # free heap top kept up to this
_STATE = {"retained": False}


def _switched_off() -> bool:
    """``RETAIN_FREED_MEMORY=0``, or the former ``VGGT_INIT_RETAIN_MEMORY=0`` (one warning)."""
    value = os.environ.get(ENV)
    if value is None and (value := os.environ.get(_OLD_ENV)) is not None:
        log.warning("%s is deprecated: set %s=%s instead", _OLD_ENV, ENV, value)
    return value == "0"


def _glibc() -> ctypes.CDLL | None:
    if not sys.platform.startswith("linux"):
        return None
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        libc.gnu_get_libc_version  # noqa: B018 (only glibc has it: musl's mallopt is a no-op)
        return libc
    except (OSError, AttributeError):
        return None


def retain_freed_memory() -> bool:
    """Serve allocations below 2 GB from the heap and keep up to 2 GB free at its top.

    Returns:
        True when the settings were applied (glibc, not switched off by
        ``RETAIN_FREED_MEMORY=0``), False otherwise.
    """
    if _switched_off():
        return False
    libc = _glibc()
    if libc is None:
        return False
    ok = (bool(libc.mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD))
          and bool(libc.mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD)))
    if not ok:
        log.warning("glibc refused the malloc settings; freed memory goes back to the system")
    _STATE["retained"] = ok
    return ok


def release_free_memory() -> bool:
    """Return whole free pages of the heap to the system (``malloc_trim(0)``); True if any were."""
    libc = _glibc()
    return bool(libc.malloc_trim(0)) if libc is not None else False


class _Mallinfo2(ctypes.Structure):
    _fields_ = [(name, ctypes.c_size_t) for name in
                ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks", "uordblks",
                 "fordblks", "keepcost")]


def heap_stats() -> dict[str, int] | None:
    """glibc's own bookkeeping of the main arena (``mallinfo2``), in bytes; None without glibc 2.33+.

    Keys: ``arena`` (heap obtained with sbrk), ``mmapped`` (bytes in blocks served by their own
    mmap, glibc's ``hblkhd``), ``mmapped_blocks`` (``hblks``), ``in_use`` (``uordblks``),
    ``free_in_heap`` (``fordblks``: freed bytes the process keeps). These are exact and depend
    only on the allocation sequence, not on what the kernel does with the pages (reclaim,
    huge-page splits), so they show whether a block was mmap'd or kept in the heap.
    """
    libc = _glibc()
    fn = getattr(libc, "mallinfo2", None) if libc is not None else None
    if fn is None:
        return None
    fn.restype = _Mallinfo2
    m = fn()
    return {"arena": m.arena, "mmapped": m.hblkhd, "mmapped_blocks": m.hblks, "in_use": m.uordblks,
            "free_in_heap": m.fordblks}


def memory_retained() -> bool:
    """Whether :func:`retain_freed_memory` is in effect in this process."""
    return _STATE["retained"]
