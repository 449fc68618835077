"""The allocator settings keep freed image buffers in the process (known
effect: page faults of a loop that allocates and frees a 40 MB array)."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt")

from napari_imgreg import _allocator
from napari_imgreg.registration.batch import THREAD_ENV_VARS, worker_environment

# malloc, fill and free a 40 MB buffer 30 times, as OpenCV, Embree and the
# splat renderer do with their image-sized scratch (NumPy's own large arrays
# ask the kernel for huge pages and fault far less); report the page faults.
_LOOP = """
import ctypes, json, resource, sys
from napari_imgreg._allocator import tune_allocator
tuned = tune_allocator() if sys.argv[1] == "tune" else False
libc = ctypes.CDLL("libc.so.6")
libc.malloc.restype, libc.malloc.argtypes = ctypes.c_void_p, [ctypes.c_size_t]
libc.free.argtypes = [ctypes.c_void_p]
size = 40 << 20
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(30):
    p = libc.malloc(size)
    ctypes.memset(p, 1, size)
    libc.free(p)
print(json.dumps({"tuned": tuned,
                  "faults": resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before}))
"""


def _faults(mode: str, env_extra: dict | None = None) -> dict:
    import os

    env = {**os.environ, **(env_extra or {})}
    env.pop("MALLOC_TRIM_THRESHOLD_", None)
    env.pop("MALLOC_MMAP_THRESHOLD_", None)
    out = subprocess.run([sys.executable, "-c", _LOOP, mode], capture_output=True, text=True,
                         env=env, check=True, timeout=60)
    return json.loads(out.stdout)


def test_tuned_process_reuses_freed_buffers_instead_of_faulting_them_in_again():
    plain = _faults("plain")
    tuned = _faults("tune")
    assert tuned["tuned"] and not plain["tuned"]
    # Above glibc's 32 MiB mmap ceiling each buffer is a fresh mapping whose
    # 10,240 pages are faulted in again: 30 x 10,240 = 307 k. Tuned, the first
    # buffer's pages are reused from the heap: ~10 k.
    assert plain["faults"] > 30 * 10_240 * 0.9
    assert tuned["faults"] < 2 * 10_240


def test_opt_out_leaves_the_allocator_alone(monkeypatch):
    monkeypatch.setenv(_allocator.OPT_OUT_VARIABLE, "default")
    assert _allocator.allocator_environment() == {}
    result = _faults("tune", {_allocator.OPT_OUT_VARIABLE: "default"})
    assert not result["tuned"] and result["faults"] > 200_000


def test_local_workers_start_tuned_and_pinned_replacing_dasks_trim(monkeypatch):
    monkeypatch.delenv(_allocator.OPT_OUT_VARIABLE, raising=False)
    env = worker_environment(3, {"MALLOC_TRIM_THRESHOLD_": 65536, "PYTHONHASHSEED": 7})
    assert env["MALLOC_TRIM_THRESHOLD_"] == str(_allocator.TRIM_THRESHOLD_BYTES)
    assert env["MALLOC_MMAP_THRESHOLD_"] == str(_allocator.MMAP_THRESHOLD_BYTES)
    assert env["PYTHONHASHSEED"] == "7"  # Dask's own variables are kept
    assert all(env[name] == "3" for name in THREAD_ENV_VARS)
    assert all(isinstance(v, str) for v in env.values())
