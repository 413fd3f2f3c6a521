"""Where benchmark cells run (issue #9): in process, in a spawn-based process pool, or on a Dask
cluster — three ``concurrent.futures.Executor``s driven by the one runner ``reports.runner.run_cells``.

* ``local`` — in this process, one cell after the other (the cell keeps the default thread counts).
* ``processes`` — a ``ProcessPoolExecutor`` of spawned workers on this machine.
* ``dask`` — Dask distributed: an embedded ``LocalCluster`` (processes, 1 thread per worker, bound
  to 127.0.0.1), or an existing scheduler (``scheduler="tcp://host:8786"``).

Thread discipline: every worker gets its share of its machine's cores, ``cores // task slots on
that machine`` (at least 1), in the environment variable ``PRTBENCH_THREADS``; each task sets torch
and Dr.Jit to it (``reports.measure_cell.task_threads``) and records it in the results (``threads``).

Honest timings: the parallel executors (``parallel = True``) get every cell as an *errors* task
and a *timing* task (``reports.measure_cell.run_part``). Timing tasks run one at a time per machine:
``processes`` lets at most one be in flight (``timing_in_flight = 1``); ``dask`` submits them with
the resource ``TIMING=1``, which exactly one worker per machine holds (``TimingSlotPlugin``: the
worker that takes a per-machine lock file advertises it; when it dies the lock is released and its
replacement takes it). Error tasks run on every worker. ``describe()`` (executor, workers,
scheduler) is recorded with every result, so the report says which executor produced each number.

Results are written by the workers into the run directory, so on a multi-machine cluster ``--out``
must be on a file system every worker sees (as is the reference cache, ``PRTBENCH_CACHE``).
"""
from __future__ import annotations

import concurrent.futures as cf
import multiprocessing as mp
import os
from concurrent.futures.process import BrokenProcessPool
from typing import Any

from reports.cells import THREADS_ENV

EXECUTORS = ("local", "processes", "dask")
TIMING_RESOURCE = "TIMING"
LOCK_DIR_ENV = "PRTBENCH_TIMING_LOCK_DIR"  # where workers keep the per-machine timing lock (default: temp dir)
SLOTS_MIN = 16  # tasks the runner keeps submitted to a Dask cluster (at least)


def machine_cores() -> int:
    """Cores this process may use (its CPU affinity), at least 1."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not Linux
        return max(1, os.cpu_count() or 1)


def share_of_cores(cores: int, slots: int) -> int:
    """Threads per task when ``slots`` tasks share ``cores`` cores: ``cores // slots``, at least 1."""
    if cores < 1 or slots < 1:
        raise ValueError(f"cores and slots must be >= 1, got {cores}, {slots}")
    return max(1, cores // slots)


ORPHAN_POLL_S = 1.0  # how often a pool worker checks that the process that started it is alive


def _exit_with_parent() -> None:
    """A pool worker ends when the process that started it is gone: killed (SIGKILL, a session's end, an
    interrupted run) it cannot shut its pool down, and its worker — a cell's precomputation, a timed frame —
    would run on as an orphan, taking a core from whatever is measured next (session 36: a killed prewarm's
    child ran 5 CPU-minutes into a perf run). A daemon thread checks once a second (`ORPHAN_POLL_S`) that
    the parent is still the same process and otherwise exits at once (no results: the run was gone)."""
    import threading
    import time

    known = mp.parent_process()      # the pid the parent had when it started us: a parent killed before this
    parent = known.pid if known is not None and known.pid else os.getppid()   # initializer ran is gone too

    def watch() -> None:
        while True:
            time.sleep(ORPHAN_POLL_S)
            if os.getppid() != parent:
                os._exit(3)

    threading.Thread(target=watch, name="prtbench-orphan-watch", daemon=True).start()


def _init_worker(threads: int) -> None:
    """Process-pool initializer: the worker's thread share (read per task by ``task_threads``); the worker
    ends with its parent (`_exit_with_parent`)."""
    _exit_with_parent()
    os.environ[THREADS_ENV] = str(int(threads))
    import torch

    torch.set_num_threads(int(threads))


class BenchExecutor(cf.Executor):
    """A ``concurrent.futures.Executor`` plus what the runner needs to keep timings honest.

    name, workers (processes that run tasks), slots (tasks worth keeping in flight), parallel
    (split cells into error and timing tasks), timing_in_flight (runner-side cap on timing tasks,
    None when the scheduler serialises them), ``submit_timing`` (timing work), ``describe()``.
    """

    name = "?"
    workers = 1
    slots = 1
    parallel = False
    timing_in_flight: int | None = 1

    def submit_timing(self, fn, /, *args, **kwargs) -> cf.Future:
        return self.submit(fn, *args, **kwargs)

    def describe(self) -> dict[str, Any]:
        return {"executor": self.name, "workers": self.workers}

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.describe()})"


class LocalExecutor(BenchExecutor):
    """The in-process executor: ``submit`` runs the call at once and returns a finished future
    (an exception is delivered through the future, as a pool would)."""

    name = "local"

    def submit(self, fn, /, *args, **kwargs) -> cf.Future:
        f: cf.Future = cf.Future()
        try:
            f.set_result(fn(*args, **kwargs))
        except BaseException as e:  # noqa: BLE001
            f.set_exception(e)
        return f


METHOD_PROCESS_ENV = "PRTBENCH_METHOD_PROCESS"  # set inside a MethodProcessExecutor's child


class _OrphanCell:
    """A stand-in cell for tests of `MethodProcessExecutor` (its ``submit`` groups by method and config)."""
    method, config = "test", "{}"


def _orphan_test_sleep(cell, seconds: float = 600.0) -> None:
    """A task that sleeps (tests: a worker busy when its parent is killed)."""
    import time

    time.sleep(seconds)


def _init_method_process() -> None:
    _exit_with_parent()
    os.environ[METHOD_PROCESS_ENV] = "1"


class MethodProcessExecutor(BenchExecutor):
    """Each method configuration's cells in one spawned process of their own, one process at a time
    (cells with ``isolate="method"``, the perf suite's setting; ``reports.pipeline.run_suite`` uses
    it in place of the local executor).

    Why (issue 14, sessions 32-33): run in one process, a cell's frame times depended on the cells
    other methods had run before it — ZH's order-8 L frames read 2.5-2.8 ms in two full perf runs
    and 1.2-1.4 ms alone or in a third full run, with the cause not found (candidates: native
    libraries' OpenMP teams, the oracle's work arrays and Mitsuba scenes, allocator state). A
    process per method configuration measures each method after only its own cells, for ~6 s of
    imports per configuration instead of per cell (``isolate=True``). ``group_of`` tells the runner
    how to order its queue (one process per configuration, not per scene); the previous process
    exits (``shutdown(wait=True)``) before the next one starts, so two never share the cores. A
    process that died is replaced by a fresh one for the retry (``BrokenProcessPool``)."""

    name = "method-processes"

    def __init__(self) -> None:
        self._pool: cf.ProcessPoolExecutor | None = None
        self._group: tuple[str, str] | None = None
        self.processes = 0  # how many processes this executor started (tests)

    @staticmethod
    def group_of(cell) -> tuple[str, str]:
        return (cell.method, cell.config)

    def _start(self, group: tuple[str, str]) -> None:
        self._close()
        self._pool = cf.ProcessPoolExecutor(max_workers=1, mp_context=mp.get_context("spawn"),
                                            initializer=_init_method_process)
        self._group = group
        self.processes += 1

    def _close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None

    def submit(self, fn, /, *args, **kwargs) -> cf.Future:
        group = self.group_of(args[0])  # run_cell / run_part: the cell comes first
        if self._pool is None or group != self._group:
            self._start(group)
        try:
            return self._pool.submit(fn, *args, **kwargs)
        except BrokenProcessPool:
            self._start(group)
            return self._pool.submit(fn, *args, **kwargs)

    def pids(self) -> list[int]:
        return [p.pid for p in (getattr(self._pool, "_processes", None) or {}).values() if p.is_alive()]

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=wait, cancel_futures=cancel_futures)
            self._pool = None


class ProcessesExecutor(BenchExecutor):
    """A spawn-based process pool of ``workers`` processes, ``cores // workers`` threads each.

    A pool whose worker died is broken for good (``BrokenProcessPool``): the next ``submit``
    starts a fresh pool, so the runner can re-run the lost tasks."""

    name = "processes"
    parallel = True
    timing_in_flight = 1  # one machine: the runner keeps one timing task in flight

    def __init__(self, workers: int | None = None, *, threads: int | None = None) -> None:
        cores = machine_cores()
        self.workers = self.slots = int(workers or cores)
        if self.workers < 1:
            raise ValueError("workers must be >= 1")
        self.threads = int(threads or share_of_cores(cores, self.workers))
        self._pool = self._new_pool()

    def _new_pool(self) -> cf.ProcessPoolExecutor:
        return cf.ProcessPoolExecutor(max_workers=self.workers, mp_context=mp.get_context("spawn"),
                                      initializer=_init_worker, initargs=(self.threads,))

    def submit(self, fn, /, *args, **kwargs) -> cf.Future:
        try:
            return self._pool.submit(fn, *args, **kwargs)
        except BrokenProcessPool:
            self._pool.shutdown(wait=False, cancel_futures=True)
            self._pool = self._new_pool()
            return self._pool.submit(fn, *args, **kwargs)

    def pids(self) -> list[int]:
        """Process ids of the pool's live workers (tests kill one)."""
        return [p.pid for p in (getattr(self._pool, "_processes", None) or {}).values() if p.is_alive()]

    def describe(self) -> dict[str, Any]:
        return {"executor": self.name, "workers": self.workers, "threads_per_worker": self.threads}

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        self._pool.shutdown(wait=wait, cancel_futures=cancel_futures)


# -- Dask -------------------------------------------------------------------------------------


try:
    from distributed.diagnostics.plugin import WorkerPlugin as _WorkerPlugin
except ImportError:  # pragma: no cover - dask not installed: only the dask executor needs it
    _WorkerPlugin = object


class TimingSlotPlugin(_WorkerPlugin):
    """Dask worker plugin: sets the worker's thread share and gives the ``TIMING`` resource to one
    worker per machine (per scheduler).

    ``shares``: host → threads per task, computed by the client from the workers it saw; a worker
    on a host not in it (joined later) takes ``cores // its nthreads``. The ``TIMING`` slot goes to
    the worker that takes a non-blocking ``flock`` on a per-machine lock file; the OS releases the
    lock when that worker dies, and the worker that replaces it takes it. (A worker started with
    ``--resources TIMING=1`` keeps it and takes no lock — so do not start workers that way: the
    plugin would hand a second slot to another worker of the same machine.)
    """

    name = "prtbench-timing-slot"

    def __init__(self, scheduler: str, shares: dict[str, int], lock_dir: str | None = None) -> None:
        self.scheduler = scheduler
        self.shares = dict(shares)
        self.lock_dir = lock_dir
        self._fd: int | None = None

    def lock_path(self) -> str:
        import hashlib
        import tempfile

        h = hashlib.sha1(self.scheduler.encode()).hexdigest()[:12]
        return os.path.join(self.lock_dir or tempfile.gettempdir(), f"prtbench-timing-{h}.lock")

    async def setup(self, worker) -> None:
        import fcntl

        host = worker.address.split("://")[-1].rsplit(":", 1)[0]
        threads = self.shares.get(host) or share_of_cores(machine_cores(), max(1, worker.state.nthreads))
        _init_worker(threads)
        if worker.state.total_resources.get(TIMING_RESOURCE):
            return
        fd = os.open(self.lock_path(), os.O_RDWR | os.O_CREAT, 0o600)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:  # another worker of this machine holds the timing slot
            os.close(fd)
            return
        self._fd = fd
        await worker.set_resources(**{TIMING_RESOURCE: 1})
        await _schedule_waiting_tasks(worker)

    async def teardown(self, worker) -> None:
        if self._fd is None:
            return
        try:  # give the slot up, so a re-registered plugin hands it out afresh
            await worker.set_resources(**{TIMING_RESOURCE: 0})
        except Exception:  # noqa: BLE001 - the worker is closing
            pass
        finally:
            os.close(self._fd)  # releases the flock
            self._fd = None


async def _schedule_waiting_tasks(worker) -> None:
    """Tell the scheduler to place the tasks waiting for a resource ("no-worker") now that
    ``worker`` offers one: the scheduler re-checks them when a worker *joins*, not when a worker's
    resources change (distributed 2026.8 ``Scheduler.add_resources``), so timing tasks submitted
    while the TIMING worker was restarting would wait for ever."""
    from distributed.protocol.pickle import dumps

    def schedule(address, dask_scheduler=None):  # local: pickled by value, the scheduler needs no prtbench
        import time as _time

        ws = dask_scheduler.workers.get(address)
        if ws is None:
            return 0
        recs = dask_scheduler.bulk_schedule_unrunnable_after_adding_worker(ws)
        if recs:
            dask_scheduler.transitions(recs, stimulus_id=f"prtbench-timing-slot-{_time.time()}")
        return len(recs)

    try:
        await worker.scheduler.run_function(function=dumps(schedule), args=dumps((worker.address,)),
                                            kwargs=dumps({}), wait=True)
    except Exception:  # noqa: BLE001 - e.g. a scheduler that refuses pickled functions
        import logging

        logging.getLogger(__name__).warning("could not ask the scheduler to place waiting timing tasks",
                                            exc_info=True)


def _worker_facts(dask_worker) -> dict:
    return {"cores": machine_cores(), "nthreads": dask_worker.state.nthreads,
            "host": dask_worker.address.split("://")[-1].rsplit(":", 1)[0]}


class DaskExecutor(BenchExecutor):
    """Cells on Dask distributed: an embedded ``LocalCluster`` (``workers`` processes × 1 thread,
    127.0.0.1, no dashboard) or the scheduler at ``scheduler``. Error tasks go anywhere; timing
    tasks need the ``TIMING`` resource (one worker per machine, ``TimingSlotPlugin``)."""

    name = "dask"
    parallel = True
    timing_in_flight = None  # the scheduler serialises timing work through the TIMING resource

    def __init__(self, workers: int | None = None, *, scheduler: str | None = None, threads_per_worker: int = 1,
                 timeout: float = 60.0, lock_dir: str | None = None) -> None:
        try:
            import dask
            from distributed import Client, LocalCluster
        except ImportError as e:  # pragma: no cover - depends on the installation
            raise ValueError("the dask executor needs `pip install dask[distributed]`") from e
        self.cluster = None
        self._lock_tmp = None
        lock_dir = lock_dir or os.environ.get(LOCK_DIR_ENV)
        if scheduler:
            try:
                self.client = Client(scheduler, timeout=timeout, set_as_default=False)
            except OSError as e:
                raise ValueError(f"cannot reach the Dask scheduler at {scheduler}: {e}") from None
        else:
            n = int(workers or machine_cores())
            if n < 1:
                raise ValueError("workers must be >= 1")
            # non-daemonic workers may spawn children (isolated cells); the nannies still reap them
            with dask.config.set({"distributed.worker.daemon": False}):
                self.cluster = LocalCluster(n_workers=n, threads_per_worker=threads_per_worker, processes=True,
                                            host="127.0.0.1", dashboard_address=None, scheduler_port=0)
            self.client = Client(self.cluster, set_as_default=False)
            if lock_dir is None:
                import tempfile

                self._lock_tmp = tempfile.TemporaryDirectory(prefix="prtbench-dask-")
                lock_dir = self._lock_tmp.name
        try:
            if workers and scheduler:
                self.client.wait_for_workers(int(workers), timeout=timeout)
            elif scheduler:
                self.client.wait_for_workers(1, timeout=timeout)
            facts = self.client.run(_worker_facts)
            slots: dict[str, int] = {}
            cores: dict[str, int] = {}
            for f in facts.values():
                slots[f["host"]] = slots.get(f["host"], 0) + f["nthreads"]
                cores[f["host"]] = f["cores"]
            self.shares = {h: share_of_cores(cores[h], slots[h]) for h in slots}
            self.scheduler = self.client.scheduler.address
            self.client.register_plugin(TimingSlotPlugin(self.scheduler, self.shares, lock_dir),
                                        name=TimingSlotPlugin.name)
            self.workers = len(facts)
            # keep the scheduler supplied: while the TIMING worker works through timing tasks the
            # others must find error tasks queued
            self.slots = max(SLOTS_MIN, 4 * sum(slots.values()))
            self.hosts = len(slots)
            self._wait_for_timing_slots(timeout)
        except BaseException:
            self.shutdown()
            raise
        self._any = self.client.get_executor(pure=False)
        self._timing = self.client.get_executor(pure=False, resources={TIMING_RESOURCE: 1})

    def _wait_for_timing_slots(self, timeout: float) -> None:
        import time

        t0 = time.monotonic()
        while True:
            ws = self.client.scheduler_info(n_workers=-1)["workers"].values()
            if sum(1 for w in ws if w.get("resources", {}).get(TIMING_RESOURCE)) >= self.hosts:
                return
            if time.monotonic() - t0 > timeout:
                raise ValueError(f"no worker took the {TIMING_RESOURCE} resource within {timeout} s")
            time.sleep(0.05)

    def submit(self, fn, /, *args, **kwargs) -> cf.Future:
        return self._any.submit(fn, *args, **kwargs)

    def submit_timing(self, fn, /, *args, **kwargs) -> cf.Future:
        return self._timing.submit(fn, *args, **kwargs)

    def worker_pids(self) -> dict[str, int]:
        """Worker address → process id (tests kill one)."""
        return self.client.run(os.getpid)

    def describe(self) -> dict[str, Any]:
        return {"executor": self.name, "workers": self.workers, "hosts": self.hosts,
                "scheduler": "LocalCluster" if self.cluster is not None else self.scheduler,
                "threads_per_task": self.shares}

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        """Close the client (and the embedded cluster). The runner has collected every result by
        now, so leftover futures are cancelled rather than awaited: awaiting one whose result sat on
        a dead worker would make the scheduler compute it again. On an existing cluster the worker
        plugin stays (another run may be using the TIMING slots); the next run re-registers it."""
        for name in ("_any", "_timing"):
            ex = getattr(self, name, None)
            if ex is not None:
                ex.shutdown(wait=False)
        client = getattr(self, "client", None)
        if client is not None:
            client.close()
        if self.cluster is not None:
            self.cluster.close()
            self.cluster = None
        if getattr(self, "_lock_tmp", None) is not None:
            self._lock_tmp.cleanup()
            self._lock_tmp = None


def make_executor(name: str = "local", *, workers: int | None = None, scheduler: str | None = None) -> BenchExecutor:
    """``local`` | ``processes`` (``workers`` spawned processes, default: one per core) | ``dask``
    (``scheduler`` address, or an embedded ``LocalCluster`` of ``workers`` processes)."""
    if scheduler and name != "dask":
        raise ValueError("--scheduler needs --executor dask")
    if workers is not None and workers < 1:
        raise ValueError("workers must be >= 1")
    if name == "local":
        return LocalExecutor()
    if name == "processes":
        return ProcessesExecutor(workers)
    if name == "dask":
        return DaskExecutor(workers, scheduler=scheduler)
    raise ValueError(f"unknown executor {name!r} (available: {', '.join(EXECUTORS)})")
