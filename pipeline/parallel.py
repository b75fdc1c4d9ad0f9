"""Run independent tasks (one per NeRF window) on a dask.distributed cluster with live progress.

Tasks report progress by calling `report(task_key, done, total, phase=..., **info)` inside the worker,
which puts a message on a distributed Queue; the caller's process drains it into one progress tracker
per task (pipeline/progress.py: a bar on a terminal, lines in a log), so progress made inside worker
processes reaches the user's stderr.
A task that raises does not stop the others: its exception is returned in its slot.
Inside a `shared_cluster` block (a campaign), every map_tasks call of the process, from any thread,
submits to one cluster opened on first use, so several rows' windows share its workers.
On a local cluster of its own, map_tasks can let the last tasks take the cores that finished tasks free
(`idle_threads`): each running task raises its torch threads to its share of the idle task slots the next
time it reports progress, so the last window of a row does not fit on one core while the others sit idle.
In-process work that numpy or a C library runs with the GIL released (synthetic frames, fused frames) goes
through `in_order`: a few threads, results in input order.
"""
from __future__ import annotations

import contextlib
import logging
import os
import threading
import time
import uuid
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from itertools import islice
from typing import Any

from pipeline import progress


@dataclass
class TaskOutcome:
    key: str
    result: Any = None
    error: BaseException | None = None
    seconds: float = 0.0
    worker: str = ""
    """name of the dask worker that ran the task ('' if unknown, e.g. it failed)."""
    threads: int = 0
    """the most torch threads the task used (more than it started with where it took idle cores; 0 = unknown)."""


_QUEUE_NAME: str | None = None


@dataclass
class _IdleShare:
    """Inside a task started with idle_threads: where the caller publishes the idle slots, and this task's
    thread count so far."""

    variable: str
    base_threads: int
    threads: int
    checked_at: float = 0.0


_IDLE: _IdleShare | None = None
IDLE_CHECK_S = 2.0
"""Seconds between two looks of a running task at the idle slots (each look is a round trip to the scheduler)."""


def in_order(fn: Callable[[Any], Any], items: Iterable, threads: int) -> Iterator[Any]:
    """fn(item) for every item, in the items' order, computed by `threads` threads (1: in this thread) at most
    2 x threads items ahead of the consumer, so only a few items' results are held at once."""
    if threads <= 1:
        yield from map(fn, items)
        return
    it = iter(items)
    with ThreadPoolExecutor(threads) as pool:
        ahead = deque(pool.submit(fn, x) for x in islice(it, 2 * threads))
        while ahead:
            done = ahead.popleft().result()
            ahead.extend(pool.submit(fn, x) for x in islice(it, 1))
            yield done


def available_cores() -> int:
    """The cores this process may run on (its CPU affinity where the platform has one)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def report(key: str, done: int, total: int, **info: Any) -> None:
    """Called inside a task: publish progress (no-op outside a cluster run)."""
    name = os.environ.get("PAG_PROGRESS_QUEUE") or _QUEUE_NAME
    if not name:
        return
    try:
        from distributed import Queue, get_client

        Queue(name, client=get_client()).put((key, done, total, info))
    except Exception:  # progress must never break a fit
        pass
    _take_idle_threads()


def _take_idle_threads() -> None:
    """Inside a task started with idle_threads: raise torch's threads to base x (1 + the idle slots per running
    task the caller last published); never lowered, since no new task comes to this cluster."""
    share = _IDLE
    if share is None or time.monotonic() - share.checked_at < IDLE_CHECK_S:
        return
    share.checked_at = time.monotonic()
    try:
        from distributed import Variable, get_client

        extra = int(Variable(share.variable, client=get_client()).get(timeout=1))
    except Exception:  # a missed look only keeps the threads as they are
        return
    want = share.base_threads * (1 + max(0, extra))
    if want > share.threads:
        import torch

        torch.set_num_threads(want)
        share.threads = want


def keep_freed_memory() -> bool:
    """Let glibc keep freed heap memory for reuse (mmap threshold 32 MiB, trim threshold 64 MiB: the
    values its adaptive scheme reaches on its own in a plain process). Dask workers start with
    MALLOC_TRIM_THRESHOLD_ set, which turns that scheme off, so each large tensor is mmap'ed, zeroed
    by page faults and unmapped again. False where the C library is not glibc."""
    import ctypes
    import ctypes.util

    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        m_trim_threshold, m_mmap_threshold = -1, -3
        return bool(libc.mallopt(m_mmap_threshold, 32 << 20)) and bool(libc.mallopt(m_trim_threshold, 64 << 20))
    except (OSError, AttributeError):
        return False


def worker_name() -> str:
    """Name of the dask worker running the calling task ('' outside a worker)."""
    try:
        from distributed import get_worker

        return str(get_worker().name)
    except (ImportError, ValueError):
        return ""


def _worker_threads() -> int:
    """Cores of this worker's machine per task slot of the worker."""
    from distributed import get_worker

    try:
        slots = get_worker().state.nthreads
    except (ValueError, AttributeError):
        slots = 1
    return max(1, (os.cpu_count() or 1) // max(1, slots))


def _run_task(fn: Callable, payload: Any, queue_name: str, threads: int, idle_variable: str | None = None
              ) -> tuple[Any, float, str, int]:
    """fn(payload) with `threads` torch threads (0 = the worker's share of its machine); returns the result, its
    seconds, the worker's name and the most threads the task used."""
    global _QUEUE_NAME, _IDLE
    import torch

    _QUEUE_NAME = queue_name
    keep_freed_memory()  # also on workers of a cluster this process did not start (--scheduler)
    base = threads if threads > 0 else _worker_threads()
    torch.set_num_threads(base)
    _IDLE = _IdleShare(idle_variable, base, base, time.monotonic()) if idle_variable else None
    t0 = time.perf_counter()
    try:
        return fn(payload), time.perf_counter() - t0, worker_name(), _IDLE.threads if _IDLE else base
    finally:
        _QUEUE_NAME, _IDLE = None, None


def idle_slots(n_workers: int, unfinished: int) -> int:
    """Idle task slots each running task may take: none while the queue still fills every worker, then the
    free workers shared equally (rounded down) among the tasks left. Example: 4 workers, 2 tasks left -> 1."""
    if unfinished <= 0 or unfinished >= n_workers:
        return 0
    return (n_workers - unfinished) // unfinished


def default_workers(n_tasks: int, device: str = "cpu") -> int:
    """Workers of a local cluster for n_tasks tasks on torch `device`: one per core on the CPU, one per GPU that
    torch sees for 'cuda' (all GPUs), one for 'cuda:N'; never more than the tasks."""
    if device.startswith("cuda"):
        import torch

        return max(1, min(n_tasks, torch.cuda.device_count() if device == "cuda" else 1))
    return max(1, min(n_tasks, os.cpu_count() or 1))


def spread_over_gpus(device: str, task_index: int) -> str:
    """The device of the task_index-th task: 'cuda' on a machine of several GPUs takes them in turn
    ('cuda:0', 'cuda:1', ...), so that one worker per GPU fits on its own GPU; any other device is kept."""
    if device != "cuda":
        return device
    import torch

    n = torch.cuda.device_count()
    return f"cuda:{task_index % n}" if n > 1 else device


@contextlib.contextmanager
def client_for(scheduler: str | None, n_workers: int, threads_per_worker: int) -> Iterator[Any]:
    """A Client on an existing scheduler, or on a local process cluster sized as asked."""
    from distributed import Client, LocalCluster

    for name in ("distributed", "distributed.nanny", "distributed.scheduler", "distributed.core"):
        logging.getLogger(name).setLevel(logging.ERROR)
    # The client is not entered as a context manager: that sets dask's current-client context variable,
    # which must be reset in the same context, and a campaign opens its shared client from a row's thread
    # and closes it from the main one.
    if scheduler:
        client = Client(scheduler, timeout="30s")
        try:
            yield client
        finally:
            client.close()
        return
    import dask

    env = {"OMP_NUM_THREADS": str(threads_per_worker), "MKL_NUM_THREADS": str(threads_per_worker)}
    # Dask's nanny sets MALLOC_TRIM_THRESHOLD_ in its workers, which turns off glibc's adaptive mmap
    # threshold: every large tensor is then mmap'ed, page-faulted and unmapped anew, and half of a fit's
    # CPU time went to the kernel (default row: 0.31 s per training step in a worker vs 0.15 s in a plain
    # process; `pag bench dask` times it). None removes the variable from the workers' environment.
    with dask.config.set({"distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None}), \
            LocalCluster(n_workers=n_workers, threads_per_worker=1, processes=True, dashboard_address=None,
                         silence_logs=40, env=env) as cluster:
        client = Client(cluster)
        try:
            yield client
        finally:
            client.close()


@dataclass
class _Shared:
    scheduler: str | None
    n_workers: int
    threads_per_worker: int
    """torch threads per task; 0 = decided on each worker (its cores / its task slots)."""
    client: Any = None
    stack: contextlib.ExitStack | None = None


_SHARED: _Shared | None = None
_SHARED_LOCK = threading.Lock()


@contextlib.contextmanager
def shared_cluster(scheduler: str | None, n_workers: int, threads_per_worker: int) -> Iterator[None]:
    """Within the block, map_tasks (from any thread of this process) submits to one cluster: the scheduler
    at `scheduler`, or a local cluster of `n_workers` processes started on first use and closed at the end."""
    global _SHARED
    if _SHARED is not None:
        raise RuntimeError("shared_cluster blocks cannot be nested")
    _SHARED = _Shared(scheduler, n_workers, threads_per_worker)
    try:
        yield
    finally:
        shared, _SHARED = _SHARED, None
        if shared.stack is not None:
            shared.stack.close()


def _shared_client() -> Any:
    with _SHARED_LOCK:
        if _SHARED.client is None:
            _SHARED.stack = contextlib.ExitStack()
            _SHARED.client = _SHARED.stack.enter_context(
                client_for(_SHARED.scheduler, _SHARED.n_workers, max(1, _SHARED.threads_per_worker)))
        return _SHARED.client


def task_threads(threads_per_worker: int, n_workers: int) -> int:
    """torch threads per task: the setting if > 0, else what the shared cluster says (0 = decided on the
    worker), else this machine's cores / n_workers."""
    if threads_per_worker > 0:
        return threads_per_worker
    if _SHARED is not None:
        return _SHARED.threads_per_worker
    return max(1, (os.cpu_count() or 1) // max(1, n_workers))


def own_cluster(scheduler: str | None) -> bool:
    """Whether map_tasks with this scheduler starts a local cluster of its own (no scheduler given, outside a
    shared_cluster block): only then does it control which task runs when."""
    return scheduler is None and _SHARED is None


def map_tasks(fn: Callable[[Any], Any], payloads: dict[str, Any], n_workers: int = 0, threads_per_worker: int = 0,
              scheduler: str | None = None, show_progress: bool = True, desc: str = "task",
              label: str | None = None, progress_interval_s: float = 2.0, idle_threads: bool = False,
              then: Callable[[Any], Any] | None = None) -> dict[str, TaskOutcome]:
    """Run fn(payload) for every payload; returns outcomes by key. One task per worker at a time.
    Progress of task k is shown as f"{label or desc} {k}".
    idle_threads: on a local cluster this call starts (no scheduler, no shared cluster), once fewer tasks are
    left than workers, the running tasks share the idle workers' threads (taken when they next report
    progress). Their results then depend on when that happened, to floating-point noise.
    then: a second part of every task, run as a task of its own: the outcome of k is then(fn(payload k)).
    Parts are then submitted one per worker at a time (so n_workers should be the cluster's size: a cluster
    of this call's own, see own_cluster), every first part before any second part. With three tasks on two
    workers, the third task's first part runs beside the second parts of the other two, not alone.
    fn's result travels through this process, so it should be small (a path, not a model)."""
    from distributed import Queue, Variable, as_completed

    n_workers = n_workers or default_workers(len(payloads))
    threads = task_threads(threads_per_worker, n_workers)
    outcomes: dict[str, TaskOutcome] = {}
    queue_name = f"pag-progress-{uuid.uuid4().hex[:8]}"
    opened = contextlib.nullcontext(_shared_client()) if _SHARED is not None else client_for(scheduler, n_workers, threads)
    share = idle_threads and scheduler is None and _SHARED is None and n_workers > 1
    idle_name = f"pag-idle-{uuid.uuid4().hex[:8]}" if share else None
    with opened as client:
        queue = Queue(queue_name, client=client)
        idle = Variable(idle_name, client=client) if share else None
        if idle is not None:
            idle.set(0)
        queued = deque((fn, k, p) for k, p in payloads.items())   # (part, key, its input) not yet submitted
        limit = n_workers if then is not None else len(payloads)
        running: dict[Any, str] = {}   # future -> task key
        first_part: dict[str, tuple[float, int]] = {}   # key -> seconds and threads of a finished first part
        pending = as_completed()

        def submit_queued() -> None:
            while queued and len(running) < limit:
                part, k, x = queued.popleft()
                fut = client.submit(_run_task, part, x, queue_name, threads, idle_name,
                                    key=f"{desc}-{k}-{uuid.uuid4().hex[:6]}", pure=False)
                running[fut] = k
                pending.add(fut)

        submit_queued()
        bars = {k: progress.Tracker(f"{label or desc} {k}", None, enabled=show_progress, interval_s=progress_interval_s,
                                    position=i) for i, k in enumerate(payloads)}

        def drain() -> None:
            try:
                messages = queue.get(batch=True)
            except Exception:  # progress must never break the run
                return
            for key, done, total, info in messages:
                bar = bars.get(key)
                if bar is not None:
                    info = dict(info)
                    bar.update(done, total, str(info.pop("phase", "step")), info)

        while True:
            drain()
            finished = pending.next_batch(block=False) if not pending.is_empty() else []
            for fut in finished:
                key = running.pop(fut)
                try:
                    result, seconds, worker, used = fut.result()
                    if then is not None and key not in first_part:
                        first_part[key] = (seconds, used)
                        queued.append((then, key, result))   # behind every first part still queued
                        continue
                    before, threads_before = first_part.get(key, (0.0, 0))
                    outcomes[key] = TaskOutcome(key, result=result, seconds=before + seconds, worker=worker,
                                                threads=max(used, threads_before))
                except Exception as err:  # keep going: the other tasks finish
                    outcomes[key] = TaskOutcome(key, error=err)
                drain()  # the task's last messages before its end line
                o = outcomes[key]
                bars[key].finish(f"done in {o.seconds:.1f} s" if o.error is None else
                                 f"failed: {str(o.error).splitlines()[0] if str(o.error) else type(o.error).__name__}")
            submit_queued()
            if pending.is_empty() and len(outcomes) == len(payloads):
                break
            if finished and idle is not None:
                left = len(payloads) - len(outcomes)
                idle.set(idle_slots(n_workers, left))
            time.sleep(0.3)
        drain()
        for bar in bars.values():
            bar.finish()
    return outcomes
