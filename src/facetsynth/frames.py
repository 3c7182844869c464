"""Per-frame work in parallel: the frame stages (capture, hdr, rectify) treat each frame independently.

Their work per frame is numpy arithmetic and OpenEXR / OpenImageIO I/O, which
release the GIL, so a pool of threads shares a job's cores without copying
any data between processes. Results come back in frame order.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from typing import Callable, Iterable, TypeVar

from tqdm import tqdm

T = TypeVar("T")
R = TypeVar("R")


def map_frames(work: Callable[[T], R], items: Iterable[T], threads: int, desc: str, total: int | None = None,
               unit: str = "frame") -> list[R]:
    """``[work(item) for item in items]`` on ``threads`` threads, with one progress bar.

    ``items`` may be a generator (the capture loop driving the rig): it is
    consumed in this thread, in order, while the pool works on the frames
    already produced. The first exception raised by ``work`` is re-raised.
    """
    if total is None and hasattr(items, "__len__"):
        total = len(items)  # type: ignore[arg-type]
    if threads <= 1:
        return [work(item) for item in tqdm(items, desc=desc, unit=unit, total=total)]
    with ThreadPoolExecutor(max_workers=threads) as pool:
        return list(tqdm(pool.map(work, items), desc=desc, unit=unit, total=total))
