"""Independent jobs of the data set-up (decoding and caching video frames, encoding SAM features) on a pool of
threads: their work runs in C code that releases the GIL (ffmpeg, zlib, numpy), so one thread per core shortens
the set-up of a long multi-view video by about the number of cores."""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor, as_completed
from typing import Callable, List, Optional, Sequence, TypeVar

T = TypeVar("T")


def available_cores() -> int:
    """The cores this process may run on (its CPU affinity, e.g. a container's share), at least 1."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def run_parallel(jobs: Sequence[Callable[[], T]], workers: int, done: Callable[[], None]) -> List[T]:
    """Run `jobs` on up to `workers` threads, calling `done` in this thread as each one finishes; returns their
    results in the order of `jobs`. Once a job fails, the jobs not started yet return at once without running, and
    its error is raised when the running ones have finished."""
    failed = threading.Event()

    def guarded(job: Callable[[], T]) -> Optional[T]:
        if failed.is_set():
            return None  # a job has failed, or the caller was interrupted: do not start
        try:
            return job()
        except BaseException:
            failed.set()
            raise

    with ThreadPoolExecutor(max(1, min(workers, len(jobs)))) as pool:
        futures = [pool.submit(guarded, job) for job in jobs]
        try:
            for future in as_completed(futures):
                future.result()
                done()
        except BaseException:  # an interrupt here, too, leaves the jobs not started undone
            failed.set()
            raise
    return [future.result() for future in futures]
