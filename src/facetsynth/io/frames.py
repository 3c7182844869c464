"""Per-frame and per-tile work in parallel: the frame stages (capture, hdr, rectify) treat each frame
independently, the per-point stages each tile of points.

Their work is numpy arithmetic, compiled kernels (numba, ``nogil``) and
OpenEXR / OpenImageIO I/O, which release the GIL, so a pool of threads
shares a job's cores without copying any data between processes. Results
come back in order.
"""

from __future__ import annotations

from collections import deque
from concurrent.futures import ThreadPoolExecutor
from typing import Callable, Iterable, Iterator, TypeVar

from threadpoolctl import threadpool_limits
from tqdm import tqdm

T = TypeVar("T")
R = TypeVar("R")


def imap(work: Callable[[T], R], items: Iterable[T], threads: int, desc: str, total: int | None = None,
         unit: str = "frame", ahead: int = 2) -> Iterator[R]:
    """``work(item)`` for each item, yielded in order, on ``threads`` threads, with one progress bar.

    ``items`` is consumed in this thread as the pool needs work, at most
    ``ahead`` x ``threads`` items in flight: memory holds that many results,
    never all of them (a tile stage streams its output in order). ``items``
    may be a generator (the capture loop driving the rig). The first
    exception raised by ``work`` is re-raised.
    """
    if total is None and hasattr(items, "__len__"):
        total = len(items)  # type: ignore[arg-type]
    with tqdm(total=total, desc=desc, unit=unit) as bar:
        if threads <= 1:
            for item in items:
                result = work(item)
                bar.update()
                yield result
            return
        # one BLAS thread per worker: ``threads`` workers share ``threads`` cores
        with ThreadPoolExecutor(max_workers=threads) as pool, threadpool_limits(limits=1):
            pending: deque = deque()
            for item in items:
                pending.append(pool.submit(work, item))
                if len(pending) >= ahead * threads:
                    result = pending.popleft().result()
                    bar.update()
                    yield result
            while pending:
                result = pending.popleft().result()
                bar.update()
                yield result


def map_frames(work: Callable[[T], R], items: Iterable[T], threads: int, desc: str, total: int | None = None,
               unit: str = "frame") -> list[R]:
    """``[work(item) for item in items]`` on ``threads`` threads (:func:`imap`)."""
    return list(imap(work, items, threads, desc, total, unit))
