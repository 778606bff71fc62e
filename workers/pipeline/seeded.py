"""Repeatable Open3D random draws: :func:`seeded_open3d`."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from contextlib import contextmanager

import open3d as o3d

#: held while Open3D is limited to one thread (the limit is process-wide; a nested block
#: in the same thread enters again)
_ONE_THREAD = threading.RLock()


@contextmanager
def seeded_open3d(seed: int) -> Iterator[None]:
    """Inside the block, Open3D's generator starts from ``seed`` and Open3D (oneTBB) runs on
    one thread; the thread count is restored after. Open3D's RANSACs (feature registration,
    plane segmentation) share the generator among their threads, so a seed repeats its
    result only on one. The limit is process-wide: a block in another thread waits."""
    with _ONE_THREAD:
        threads = o3d.utility.get_max_threads()
        o3d.utility.set_max_threads(1)
        try:
            o3d.utility.random.seed(seed)
            yield
        finally:
            o3d.utility.set_max_threads(threads)
