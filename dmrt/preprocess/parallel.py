"""Preprocessing past one machine: the parallel phases as Dask tasks (``dask.distributed``).

:func:`open_executor` turns ``dmrt preprocess --dask SPEC`` into an executor whose :meth:`map`
runs a module-level function over items, results in item order:

``None``
    :class:`ProcessPool` of ``workers`` local processes (the default: one per CPU core) for the CPU
    phases; the GPU phase (depth maps) stays in this process, on its one GL context. With
    ``workers=1``, :class:`InProcess`: a plain loop in this process.
``"local:N"``
    A ``LocalCluster`` of ``N`` worker processes with one thread each, closed on exit.
``"tcp://HOST:PORT"``
    A running scheduler (``dask scheduler`` + ``dask worker ... --nthreads 1`` on each machine).

On Dask every worker runs the CPU phases, but only the *GPU workers* render depth maps
(:meth:`DaskExecutor.map_gpus`): per host, its first ``g`` workers, where ``g`` is
``gpus_per_host`` (``dmrt preprocess --dask-gpus``) or else the host's NVIDIA GPUs, at least 1
(a host without them, e.g. Mesa's llvmpipe, renders on one worker) and at most the host's
workers. Each GPU worker splats its share of the cloud into every map and reads all of them back,
so ``--dask local:32`` on a 2-GPU host keeps 32 processes for the CPU phases and 2 for the maps.

Tasks take picklable arguments (paths, configurations, cameras, index ranges) and read the octree,
the normals/radii and the depth maps from the bundle's ``.partial`` work folder, so every worker
must see the bundle's folder and the scene at the same paths (a shared file system). GPU tasks make
the worker's own GL context on first use (:func:`dmrt.gl.get_context`): one context per worker
process, so a worker must run one thread. The workers of a host get ranks 0, 1, ... (by address)
and, on a host with several NVIDIA GPUs, worker ``r`` uses GPU ``r mod GPUs``
(``GLCONTEXT_DEVICE_INDEX``, unless already set): the GPU workers, ranks ``0 .. g-1``, each have
a GPU of their own.
"""

from __future__ import annotations

import os
import re
from contextlib import contextmanager
from typing import Callable, Iterator, Sequence

from dmrt.errors import ConfigError, DMRTError, require

__all__ = ["InProcess", "ProcessPool", "DaskExecutor", "open_executor", "check_gpus_per_host", "split"]

_SPEC_HELP = "expected local:N (a LocalCluster of N worker processes) or tcp://HOST:PORT (a running scheduler)"


def split(n: int, parts: int) -> list[range]:
    """``range(n)`` cut into at most ``parts`` contiguous, non-empty ranges of near-equal length."""
    parts = max(1, min(int(parts), n))
    bounds = [n * i // parts for i in range(parts + 1)]
    return [range(a, b) for a, b in zip(bounds, bounds[1:]) if b > a]


class InProcess:
    """Runs tasks here, one after the other (no Dask)."""

    spec = None
    workers = 1
    # distributed: tasks run in other processes (they read the work folder, results come back
    # pickled); gpu_tasks: those processes also run the GPU phase, each on its own GL context
    distributed = False
    gpu_tasks = False

    def map(self, fn: Callable, items: Sequence, desc: str | None = None, progress: bool = False,
            **shared) -> list:
        """``[fn(item, **shared) for item in items]``."""
        return [fn(item, **shared) for item in items]

    def imap(self, fn: Callable, items: Sequence, desc: str | None = None, progress: bool = False,
             **shared) -> Iterator:
        """:meth:`map`, one result at a time."""
        return (fn(item, **shared) for item in items)

    def record(self) -> None:
        return None


_THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


@contextmanager
def _workers_ignore_interrupts():
    """SIGINT ignored while the block starts worker processes: Ctrl-C reaches every process of the
    terminal's group, and a spawned Python keeps an ignored SIGINT ignored, so that this process
    alone answers it (one line, ``dmrt.app.cli``) rather than each worker with a traceback.
    (Handlers are set in the main thread only; elsewhere the block runs as it is.)"""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


class ProcessPool:
    """Runs tasks in ``workers`` local processes (``concurrent.futures``, spawned: the parent may
    hold a GL context or Embree threads that a fork would copy half-alive). The GPU phase stays
    in the calling process (``gpu_tasks`` False): one GPU is best fed by one context.

    ``shared`` keyword arguments of :meth:`map` travel with every task (pickled each time), so
    they should be small: paths, configurations, cameras.
    """

    spec = None
    distributed = True
    gpu_tasks = False

    def __init__(self, workers: int):
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor

        self.workers = int(workers)
        # one BLAS/OpenMP thread per worker: N workers each spinning N threads made the candidates
        # phase spend 15x its serial CPU time on 16 cores. The variables must be in the workers'
        # environment before they import numpy, so the workers start now, with them set.
        saved = {k: os.environ.get(k) for k in _THREAD_VARS}
        os.environ.update({k: "1" for k in _THREAD_VARS})
        try:
            with _workers_ignore_interrupts():
                self._pool = ProcessPoolExecutor(self.workers, mp_context=multiprocessing.get_context("spawn"))
                # every worker now: a spawned pool starts one per task submitted while none is idle
                # (Python 3.11), so one task each, submitted together; a worker started later would
                # miss the variables (and take Ctrl-C)
                for task in [self._pool.submit(int) for _ in range(self.workers)]:
                    task.result()
        finally:
            for k, v in saved.items():
                if v is None:
                    os.environ.pop(k, None)
                else:
                    os.environ[k] = v

    def close(self) -> None:
        self._pool.shutdown(wait=True, cancel_futures=True)

    def record(self) -> dict:
        return {"spec": f"processes:{self.workers}", "workers": self.workers}

    def imap(self, fn: Callable, items: Sequence, desc: str | None = None, progress: bool = False,
             **shared) -> Iterator:
        """``fn(item, **shared)`` per item, results in item order, at most ``2 * workers`` tasks
        queued ahead of the one handed over (results are not all held at once)."""
        from concurrent.futures.process import BrokenProcessPool
        from functools import partial

        from tqdm import tqdm

        task, items = partial(fn, **shared), list(items)
        window, pending = 2 * self.workers, []
        try:
            with tqdm(total=len(items), desc=desc, unit="task", disable=not progress) as bar:
                for i in range(len(items)):
                    while len(pending) < window and i + len(pending) < len(items):
                        pending.append(self._pool.submit(task, items[i + len(pending)]))
                    result = pending.pop(0).result()
                    bar.update()
                    yield result
        except BrokenProcessPool:
            raise DMRTError(f"a worker process of {desc or 'a parallel phase'} died (out of memory?): "
                            "try fewer --workers or a lower --memory-limit-mb") from None
        finally:
            for f in pending:
                f.cancel()

    def map(self, fn: Callable, items: Sequence, desc: str | None = None, progress: bool = False,
            **shared) -> list:
        """:meth:`imap` as a list."""
        return list(self.imap(fn, items, desc, progress, **shared))


class DaskExecutor:
    """Runs tasks on a ``dask.distributed`` cluster through ``client``.

    ``shared`` keyword arguments of :meth:`map` are sent to every worker once (scattered,
    broadcast) rather than once per task.

    Parameters
    ----------
    client : distributed.Client
    spec : str
        What the cluster was opened from (``local:N``, ``tcp://HOST:PORT``), for the record.
    gpu_workers : list of str
        Addresses of the workers that run the GPU phase (:meth:`map_gpus`), in order; see the
        module docstring for how :func:`open_executor` chooses them.
    """

    distributed = True
    gpu_tasks = True

    def __init__(self, client, spec: str, gpu_workers: Sequence[str]):
        self.client, self.spec, self.gpu_workers = client, spec, list(gpu_workers)
        if not self.gpu_workers:
            raise ValueError("a DaskExecutor needs at least one GPU worker")

    @property
    def workers(self) -> int:
        """Workers connected now (at least 1)."""
        return max(1, len(self.client.nthreads()))

    def record(self) -> dict:
        """What bundle.json records of the cluster."""
        return {"spec": self.spec, "workers": self.workers, "gpu_workers": len(self.gpu_workers)}

    def _scatter(self, shared, workers=None):
        return {k: self.client.scatter([v], workers=workers, broadcast=True, hash=False)[0]
                for k, v in shared.items()}

    def _submit(self, fn, items, shared):
        return self.client.map(fn, list(items), pure=False, **self._scatter(shared))

    def _gather(self, futures, desc, progress) -> list:
        from distributed import as_completed
        from tqdm import tqdm

        try:
            with tqdm(total=len(futures), desc=desc, unit="task", disable=not progress) as bar:
                for f in as_completed(futures):
                    if f.status == "error":
                        f.result()  # raises the task's exception
                    bar.update()
            return self.client.gather(futures)
        finally:
            for f in futures:
                f.release()

    def map(self, fn: Callable, items: Sequence, desc: str | None = None, progress: bool = False,
            **shared) -> list:
        """``[fn(item, **shared) for item in items]`` as tasks; a tqdm bar over completed ones.
        The first task that fails raises its exception here."""
        return self._gather(self._submit(fn, items, shared), desc, progress)

    def map_gpus(self, fn: Callable, items: Sequence, desc: str | None = None, progress: bool = False,
                 **shared) -> list:
        """:meth:`map` with ``items[i]`` run on ``gpu_workers[i]`` and nowhere else (at most one
        item per GPU worker: each holds its GPU's one GL context).

        Raises
        ------
        ValueError
            More items than GPU workers.
        DMRTError
            A GPU worker left the cluster (its task could run nowhere else).
        """
        items = list(items)
        if len(items) > len(self.gpu_workers):
            raise ValueError(f"{len(items)} GPU tasks for {len(self.gpu_workers)} GPU workers")
        targets = self.gpu_workers[:len(items)]
        gone = [a for a in targets if a not in self.client.nthreads()]
        if gone:
            raise DMRTError(f"dask GPU worker(s) {', '.join(gone)} left the cluster")
        box = self._scatter(shared, workers=targets)
        # allow_other_workers=False: a share must not land on a worker already holding one
        futures = [self.client.submit(fn, item, workers=[address], allow_other_workers=False, pure=False, **box)
                   for item, address in zip(items, targets)]
        return self._gather(futures, desc, progress)

    def imap(self, fn: Callable, items: Sequence, desc: str | None = None, progress: bool = False,
             **shared) -> Iterator:
        """:meth:`map`, results handed over (and released on the workers) one at a time, in order."""
        from tqdm import tqdm

        futures = self._submit(fn, items, shared)
        try:
            with tqdm(total=len(futures), desc=desc, unit="task", disable=not progress) as bar:
                for i in range(len(futures)):
                    result = futures[i].result()
                    futures[i].release()
                    futures[i] = None
                    bar.update()
                    yield result
        finally:
            for f in futures:
                if f is not None:
                    f.release()


def _nvidia_gpus() -> int:
    """NVIDIA GPUs of this host (``/dev/nvidia<N>`` device files); 0 without them."""
    try:
        return sum(1 for name in os.listdir("/dev") if re.fullmatch(r"nvidia\d+", name))
    except OSError:
        return 0


def _pin_gpu(rank: int) -> int | None:
    """In a worker: use GPU ``rank mod GPUs`` of its host for EGL, where the host has several
    GPUs and nothing chose one yet (the worker has made no GL context so far)."""
    n = _nvidia_gpus()
    if n > 1 and "GLCONTEXT_DEVICE_INDEX" not in os.environ:
        os.environ["GLCONTEXT_DEVICE_INDEX"] = str(rank % n)
    value = os.environ.get("GLCONTEXT_DEVICE_INDEX")
    return int(value) if value else None


# glibc's mallopt parameters (malloc.h)
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3


def _plain_heap() -> bool:
    """In a Dask worker: give glibc's heap back the reuse a plain process has. The nanny starts
    workers with ``MALLOC_TRIM_THRESHOLD_`` set (distributed's ``pre-spawn-environ``), and any
    such setting turns off glibc's dynamic mmap threshold: every array above 128 KiB is then a
    fresh ``mmap`` whose pages fault in (zeroed) on first write. The depth-map phase allocates
    ~56 bytes per point that way (chunks read, packed, read back); its 683M points took 15 s
    longer on one Dask worker than in-process (H200, before this), and a CPU loop of its
    allocations took 4.6 s with the variable, 3.3 s without, 3.0 s after this. Fixing the
    thresholds at the values the dynamic rule grows to on 64-bit (32 MiB mmap, twice that trim)
    restores the reuse; returns whether they were set (glibc only, and only where the variable
    is set)."""
    if "MALLOC_TRIM_THRESHOLD_" not in os.environ:
        return False
    try:
        import ctypes

        libc = ctypes.CDLL("libc.so.6")
        return bool(libc.mallopt(_M_MMAP_THRESHOLD, 32 << 20)) and bool(libc.mallopt(_M_TRIM_THRESHOLD, 64 << 20))
    except (OSError, AttributeError):  # not glibc
        return False


def _host(address: str) -> str:
    """``tcp://10.0.0.5:40123`` -> ``tcp://10.0.0.5``."""
    return address.rsplit(":", 1)[0]


def _spread_gpus(client) -> dict[str, int]:
    """Give the workers of each host consecutive ranks by address and pin each to GPU ``rank mod
    GPUs`` (:func:`_pin_gpu`); returns ``{address: rank}`` (workers joining later keep the
    default GPU and are not GPU workers)."""
    ranks, per_host = {}, {}
    for address in sorted(client.nthreads()):
        host = _host(address)
        ranks[address] = per_host[host] = per_host.get(host, -1) + 1
    for address, rank in ranks.items():
        client.run(_pin_gpu, rank, workers=[address])
    return ranks


def _gpu_workers(client, ranks: dict[str, int], gpus_per_host: int | None = None) -> list[str]:
    """The workers that render depth maps: per host (in address order), its workers of rank below
    ``gpus_per_host``, or without it below the host's NVIDIA GPUs as one of its workers counts
    them; at least 1 and at most the host's workers. In host order, then by rank."""
    hosts: dict[str, list[str]] = {}
    for address in sorted(ranks, key=lambda a: (_host(a), ranks[a])):
        hosts.setdefault(_host(address), []).append(address)
    chosen = []
    for addresses in hosts.values():
        g = gpus_per_host
        if g is None:  # measured where the workers run: this process may be on another machine
            g = client.run(_nvidia_gpus, workers=[addresses[0]])[addresses[0]]
        chosen += addresses[:max(1, min(int(g), len(addresses)))]
    return chosen


def default_workers() -> int:
    """Local worker processes by default: the CPU cores this process may use."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover (not Linux)
        return max(1, os.cpu_count() or 1)


def check_gpus_per_host(spec: str | None, gpus_per_host: int | None) -> None:
    """:class:`ConfigError` (``--dask-gpus``) for GPU workers per host below 1 or without a Dask spec."""
    if gpus_per_host is None:
        return
    if spec is None:
        raise ConfigError("dask_gpus", "needs --dask (without it the depth maps stay on this process's one GL "
                                       "context)")
    if int(gpus_per_host) < 1:
        raise ConfigError("dask_gpus", f"must be >= 1, not {gpus_per_host}")


@contextmanager
def open_executor(spec: str | None, progress: bool = False, workers: int | None = 1,
                  gpus_per_host: int | None = None):
    """The executor of ``spec`` (see the module docstring), closed on exit. Without a spec,
    ``workers`` local processes (None: :func:`default_workers`; 1: :class:`InProcess`).
    ``gpus_per_host``: with a spec, the workers per host that render depth maps (None: the
    host's NVIDIA GPUs, at least 1).

    Raises
    ------
    ConfigError
        A spec of neither form, a scheduler that cannot be reached / has no workers, or
        ``gpus_per_host`` below 1 or given without a spec (``--dask-gpus``).
    MissingDependencyError
        ``dask[distributed]`` is not installed.
    """
    check_gpus_per_host(spec, gpus_per_host)
    if spec is None:
        workers = default_workers() if workers is None else int(workers)
        if workers < 1:
            raise ConfigError("workers", f"{workers}: needs at least 1 process")
        if workers == 1:
            yield InProcess()
            return
        pool = ProcessPool(workers)
        try:
            yield pool
        finally:
            pool.close()
        return
    spec = str(spec).strip()
    local = re.fullmatch(r"local:(\d+)", spec)
    remote = re.fullmatch(r"tcp://([^\s:/]+|\[[0-9a-fA-F:]+\]):(\d{1,5})", spec)
    if local is None and remote is None:
        raise ConfigError("dask", f"{spec!r}: {_SPEC_HELP}")
    if local is not None and int(local.group(1)) < 1:
        raise ConfigError("dask", f"{spec!r}: local:N needs N >= 1 worker processes")
    require("distributed", "--dask", "dask")
    import logging

    from distributed import Client, LocalCluster

    cluster = client = None
    try:
        if local is not None:
            # one thread per worker: GL contexts are per process and current on one thread, and
            # numpy-heavy Python tasks scale by processes
            cluster = LocalCluster(n_workers=int(local.group(1)), threads_per_worker=1, processes=True,
                                   dashboard_address=None, silence_logs=logging.ERROR)
            client = Client(cluster)
        else:
            try:
                client = Client(spec, timeout="10s")
                client.wait_for_workers(1, timeout=60)
            except (OSError, TimeoutError) as exc:
                raise ConfigError("dask", f"cannot use the scheduler at {spec} ({exc})") from None
        ranks = _spread_gpus(client)
        client.run(_plain_heap)
        yield DaskExecutor(client, spec, _gpu_workers(client, ranks, gpus_per_host))
    finally:
        if client is not None:
            client.close()
        if cluster is not None:
            cluster.close()


def check_gpu_worker() -> None:
    """In a task: refuse a Dask worker with several threads (its one GL context is current on one
    thread only)."""
    try:
        from distributed import get_worker

        worker = get_worker()
    except (ImportError, ValueError):
        return  # not in a worker
    if worker.state.nthreads > 1:
        raise DMRTError(f"dask worker {worker.address} runs {worker.state.nthreads} threads: GPU tasks need "
                        "workers with one thread each (dask worker --nthreads 1)")
