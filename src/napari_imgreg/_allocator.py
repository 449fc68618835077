"""Keep freed image-sized buffers in the process instead of handing them back
to the kernel.

A registration allocates and frees image-sized buffers hundreds of times
(OpenCV's and Embree's scratch, renders, per-pixel 3D, flows). glibc serves anything above
its mmap threshold (dynamic, capped at 32 MiB) with a fresh ``mmap`` and
returns it with ``munmap`` on free, so every such array is zero-filled page by
page by the kernel again: on the 12-photo benchmark campaign that was 3.2 M
page faults and 13 s of system time in 73 s. Dask makes it worse, setting
``MALLOC_TRIM_THRESHOLD_=65536`` in every worker (7.1 M faults, 26 s).

:func:`tune_allocator` raises the mmap threshold to 64 MiB and the trim
threshold to 256 MiB, so those buffers are reused from the heap: 85 k faults,
under 1 s of system time, the same peak memory (measured: 436 MB either way).
It changes only where glibc takes memory from, never how much the package
asks for. ``NAPARI_IMGREG_MALLOC=default`` leaves the allocator alone. On
other C libraries (macOS, Windows, musl) it does nothing.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import sys

#: Allocations at least this large get their own mapping (bytes).
MMAP_THRESHOLD_BYTES = 64 << 20
#: Free memory at the top of the heap beyond this is returned (bytes).
TRIM_THRESHOLD_BYTES = 256 << 20
#: Set to ``default`` to keep the C library's own allocator settings.
OPT_OUT_VARIABLE = "NAPARI_IMGREG_MALLOC"

# glibc's mallopt parameter numbers (malloc.h).
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3

_tuned = False


def allocator_environment() -> dict[str, str]:
    """The same settings as environment variables, for a process about to
    start (a Dask worker: they replace Dask's own ``MALLOC_TRIM_THRESHOLD_``).

    Returns
    -------
    dict of str to str
        Empty when the user opted out.
    """
    if os.environ.get(OPT_OUT_VARIABLE, "").strip().lower() == "default":
        return {}
    return {"MALLOC_MMAP_THRESHOLD_": str(MMAP_THRESHOLD_BYTES),
            "MALLOC_TRIM_THRESHOLD_": str(TRIM_THRESHOLD_BYTES)}


def tune_allocator() -> bool:
    """Apply the thresholds to this process (once; later calls do nothing).

    Returns
    -------
    bool
        True when glibc took both settings (now or on an earlier call);
        False on another C library, or when ``NAPARI_IMGREG_MALLOC=default``.
    """
    global _tuned
    if _tuned:
        return True
    if not sys.platform.startswith("linux") or not allocator_environment():
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # not glibc (musl has no mallopt)
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    _tuned = bool(mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES)
                  and mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES))
    return _tuned
