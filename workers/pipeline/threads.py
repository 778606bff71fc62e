"""Independent pieces of work (pose fits, a capture's z-buffers) on several threads:
:func:`ordered_map`.

They hold the GIL only between their NumPy, SciPy, OpenCV and Open3D calls, which release
it for their work, so two threads keep two cores busy. Open3D's seeded RANSAC is serialised
by :func:`workers.pipeline.seeded.seeded_open3d`; everything else a fit touches is its own.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

T = TypeVar("T")
R = TypeVar("R")


def thread_count(requested: int) -> int:
    """``requested`` threads, or this process's usable cores for 0."""
    if requested > 0:
        return requested
    try:
        return max(len(os.sched_getaffinity(0)), 1)
    except AttributeError:  # not on Linux
        return max(os.cpu_count() or 1, 1)


def ordered_map(
    fn: Callable[[T], R],
    items: Sequence[T],
    threads: int,
    done: Callable[[int], None] | None = None,
) -> list[R]:
    """``[fn(x) for x in items]`` computed on up to ``threads`` threads (0: one per core).

    ``done(k)`` is called in the caller's thread after the first k results, in order; an
    exception from it or from ``fn`` is raised here once the running calls have ended and
    the calls not started are dropped."""
    n = min(thread_count(threads), len(items))
    if n <= 1:
        out = []
        for k, item in enumerate(items, start=1):
            out.append(fn(item))
            if done is not None:
                done(k)
        return out
    with ThreadPoolExecutor(max_workers=n, thread_name_prefix="work") as pool:
        futures = [pool.submit(fn, item) for item in items]
        try:
            results = []
            for k, future in enumerate(futures, start=1):
                results.append(future.result())
                if done is not None:
                    done(k)
            return results
        except BaseException:
            for future in futures:
                future.cancel()
            raise
