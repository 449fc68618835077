"""Shared by tests/test_hypothesis_*.py: strategies for hostile JSON values
and :func:`call_bounded`, which runs one reader call under a time and a
memory bound and allows only a normal return or an ``InputError``.

Bounds per call: :data:`TIME_LIMIT_S` of CPU time (a ``SIGPROF`` from
``ITIMER_PROF``, which counts the whole process, threads included),
:data:`WALL_LIMIT_S` of wall time (a ``SIGALRM``: a call blocked without
computing) and :data:`MEMORY_LIMIT_MB` of address-space growth
(``RLIMIT_AS``). The time bound is on CPU time so that it means the same on
an idle laptop and on a loaded CI runner (a wall-clock bound of 30 s failed
a 2 s call there, run under ``nice`` beside five other jobs). A reader
that sizes an array from a header field (``ncols 1e9``, ``element vertex
4000000000``) fails the memory bound long before the machine does. A reader
that catches every exception and rewords it as bad input cannot hide a bound
from the test: a bound that fired during the call, or an ``InputError`` that
names a ``MemoryError``, fails it all the same. Examples per test:
:data:`EXAMPLES` (500; the environment variable
``NAPARI_IMGREG_HYPOTHESIS_EXAMPLES`` changes it, e.g. for a longer
nightly run).
"""

from __future__ import annotations

import faulthandler
import math
import os
import resource
import signal
import time
from typing import Any, Callable

from hypothesis import HealthCheck, settings
from hypothesis import strategies as st

from napari_imgreg.errors import InputError

EXAMPLES = int(os.environ.get("NAPARI_IMGREG_HYPOTHESIS_EXAMPLES", "500"))
if os.environ.get("CI", "").lower() in ("1", "true", "yes") and EXAMPLES < 500:
    # Issue 15's bar: at least 500 examples per suite in CI; fewer only locally.
    raise RuntimeError(f"NAPARI_IMGREG_HYPOTHESIS_EXAMPLES={EXAMPLES} under CI: at least 500")
TIME_LIMIT_S = 30.0  # CPU seconds: a hang or runaway loop, not a slow call
WALL_LIMIT_S = 120.0  # a call blocked (a lock, a pipe), whatever the machine's load
MEMORY_LIMIT_MB = 1500

#: The settings of every suite: no deadline of hypothesis's own (the bound
#: is :func:`call_bounded`'s), no example database (CI is stateless).
SUITE = settings(
    max_examples=EXAMPLES,
    deadline=None,
    database=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much,
                           HealthCheck.data_too_large, HealthCheck.function_scoped_fixture],
)


class BoundExceeded(AssertionError):
    """A call ran past :data:`TIME_LIMIT_S`, :data:`WALL_LIMIT_S` or
    :data:`MEMORY_LIMIT_MB`."""


def _address_space() -> int:
    """This process's virtual size, bytes (Linux)."""
    with open("/proc/self/statm") as fh:
        return int(fh.read().split()[0]) * os.sysconf("SC_PAGE_SIZE")


#: Set by the signal handlers: a reader whose ``except Exception`` turns the
#: handler's BoundExceeded into an InputError ("cannot read LAS
#: (BoundExceeded: ...)") must still fail the test.
_FIRED: list[str] = []


def _on_cpu_limit(signum, frame):
    _FIRED.append(f"took more than {TIME_LIMIT_S} s of CPU")
    raise BoundExceeded(_FIRED[-1])


def _on_wall_limit(signum, frame):
    _FIRED.append(f"took more than {WALL_LIMIT_S} s of wall time")
    raise BoundExceeded(_FIRED[-1])


def call_bounded(fn: Callable[..., Any], *args: Any, **kwargs: Any) -> Any:
    """``fn(*args, **kwargs)``: its value, or the ``InputError`` it raised.

    Any other exception propagates (a traceback the user would see: the
    test fails with it). Bounds, enforced while the call runs: the address
    space may grow by at most :data:`MEMORY_LIMIT_MB` (``RLIMIT_AS``: an
    allocation past it is a ``MemoryError``, reported as the bound), and a
    ``SIGPROF`` after :data:`TIME_LIMIT_S` of CPU time, or a ``SIGALRM``
    after :data:`WALL_LIMIT_S` of wall time, interrupts it (a C loop that
    never returns to Python is killed by faulthandler after twice the wall
    bound).
    """
    soft, hard = resource.getrlimit(resource.RLIMIT_AS)
    limit = _address_space() + MEMORY_LIMIT_MB * 2**20
    if hard != resource.RLIM_INFINITY:
        limit = min(limit, hard)
    previous_prof = signal.signal(signal.SIGPROF, _on_cpu_limit)
    previous_alarm = signal.signal(signal.SIGALRM, _on_wall_limit)
    faulthandler.dump_traceback_later(2 * WALL_LIMIT_S, exit=True)
    resource.setrlimit(resource.RLIMIT_AS, (limit, hard))
    _FIRED.clear()
    t0, cpu0 = time.perf_counter(), time.process_time()
    signal.setitimer(signal.ITIMER_PROF, TIME_LIMIT_S)
    signal.setitimer(signal.ITIMER_REAL, WALL_LIMIT_S)
    try:
        try:
            out = fn(*args, **kwargs)
        except InputError as exc:
            message = str(exc)
            assert message.strip(), f"{type(exc).__name__} without a message"
            if any(w in message for w in ("MemoryError", "BoundExceeded", "does not fit in memory")):
                # the bound, caught by the reader and reworded as bad input
                raise BoundExceeded(f"bound reached inside the call: {message}") from None
            out = exc
        except MemoryError:
            raise BoundExceeded(f"needed more than {MEMORY_LIMIT_MB} MB") from None
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.setitimer(signal.ITIMER_PROF, 0)
        resource.setrlimit(resource.RLIMIT_AS, (soft, hard))
        faulthandler.cancel_dump_traceback_later()
        signal.signal(signal.SIGALRM, previous_alarm)
        signal.signal(signal.SIGPROF, previous_prof)
    cpu, elapsed = time.process_time() - cpu0, time.perf_counter() - t0
    if _FIRED:
        raise BoundExceeded(f"{_FIRED[0]} (the call caught the bound and went on)")
    if cpu > TIME_LIMIT_S:
        raise BoundExceeded(f"took {cpu:.1f} s of CPU (bound {TIME_LIMIT_S} s)")
    if elapsed > WALL_LIMIT_S:
        raise BoundExceeded(f"took {elapsed:.1f} s of wall time (bound {WALL_LIMIT_S} s)")
    return out


#: Numbers a careless or hostile file holds.
nasty_numbers = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([0, -1, 1, 0.0, -0.0, 1e-9, 1e308, -1e308, 2**63, -(2**63), 2**64, 10**30,
                     60000, 1e12, math.nan, math.inf, -math.inf, 359.999, 360, 720, -90, 91]),
    st.integers(min_value=-(2**70), max_value=2**70),
)

#: Any JSON-like value (what json.loads may give, NaN/Infinity included).
json_values = st.recursive(
    st.one_of(st.none(), st.booleans(), nasty_numbers, st.text(max_size=6)),
    lambda children: st.one_of(
        st.lists(children, max_size=5),
        st.dictionaries(st.text(max_size=8), children, max_size=5),
    ),
    max_leaves=6,
)


def paths_of(data: Any, prefix: tuple = ()) -> list[tuple]:
    """Every key path into nested dicts/lists (for mutating a valid document)."""
    out = [prefix] if prefix else []
    if isinstance(data, dict):
        for k, v in data.items():
            out += paths_of(v, prefix + (k,))
    elif isinstance(data, list):
        for i, v in enumerate(data):
            out += paths_of(v, prefix + (i,))
    return out


@st.composite
def mutated(draw, valid: Any, max_changes: int = 3) -> Any:
    """A deep copy of ``valid`` with a few values replaced, deleted or added."""
    import copy

    doc = copy.deepcopy(valid)
    for _ in range(draw(st.integers(1, max_changes))):
        paths = paths_of(doc)
        if not paths:
            return draw(json_values)
        path = draw(st.sampled_from(paths))
        parent = doc
        for key in path[:-1]:
            parent = parent[key]
        action = draw(st.sampled_from(["replace", "replace", "delete", "add"]))
        if action == "replace":
            parent[path[-1]] = draw(json_values)
        elif action == "delete":
            if isinstance(parent, dict):
                del parent[path[-1]]
            else:
                parent.pop(path[-1])
        elif isinstance(parent, dict):
            parent[draw(st.text(max_size=8))] = draw(json_values)
        else:
            parent.append(draw(json_values))
    return doc
