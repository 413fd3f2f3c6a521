"""Running many cells: the one loop that drives any executor (``reports.executors``).

``run_cells(cells, out_dir, executor=...)`` runs every cell not finished yet in ``out_dir`` and
returns the results in order. Finished cells are on disk as soon as they finish (``run_cell``
writes them), so a killed run resumes where it stopped; failed cells are retried.
"""
from __future__ import annotations

import os
import sys
import time
import traceback
from concurrent.futures import FIRST_COMPLETED, Future, wait
from pathlib import Path
from typing import Any, Iterable

from tqdm.auto import tqdm

from reports.cells import PARTS, STATUS_ERROR, Cell, CellResult, load_part, load_result, part_path, result_path
from reports.executors import LocalExecutor
from reports.measure_cell import merge_parts, run_cell, run_part, warm_up_compiles
from scenes.io import atomic_write_json


RETRIES_AFTER_WORKER_LOSS = 1  # a task whose worker died runs once more, alone (see ``run_cells``)


def _lost(cell: Cell, e: BaseException, part: str) -> CellResult:
    what = "" if part == "all" else f"{part} part: "
    return CellResult(cell.key(), cell.to_dict(), STATUS_ERROR, reason=f"{what}worker lost: {type(e).__name__}: {e}",
                      info={"traceback": "".join(traceback.format_exception(e)), "part": part})


def run_cells(cells: Iterable[Cell], out_dir: str | os.PathLike, *, executor=None, max_in_flight: int | None = None,
              progress: bool = True) -> list[CellResult]:
    """Run every cell not finished yet in ``out_dir``; results in the order of ``cells``.

    ``executor``: a ``concurrent.futures.Executor`` (or anything with ``submit(fn, *args, **kw) ->
    future`` whose futures have ``result()`` and ``done()``). At most ``max_in_flight`` tasks are
    submitted at once (default: the executor's ``slots``, else 1).

    An executor from ``reports.executors`` with ``parallel = True`` gets every cell as two tasks
    (``run_part``): the ``errors`` part through ``submit`` and the ``timing`` part through
    ``submit_timing`` (at most ``timing_in_flight`` of them at once, when the executor sets it),
    so timings are taken one at a time per machine while error work runs in parallel.

    Failures: a cell that raises is an ``error`` result (``execute_cell``). A task whose future
    raises (its worker died, the pool broke, the scheduler gave up) is run once more *alone* — so a
    cell that kills its worker cannot take innocent cells down with it — and recorded as an
    ``error`` result if it fails again; the rest of the sweep goes on. Finished cells are on disk
    as soon as they finish, so a re-run redoes only what failed.
    """
    cells = list(cells)
    out_dir = Path(out_dir)
    warm_up_compiles()  # a bad PRTBENCH_WARM is one clear error before any cell runs
    ex = executor or LocalExecutor()
    split = bool(getattr(ex, "parallel", False))
    context = ex.describe() if hasattr(ex, "describe") else {"executor": type(ex).__name__}
    slots = max(1, max_in_flight or getattr(ex, "slots", 1))
    timing_cap = getattr(ex, "timing_in_flight", None)
    results: dict[int, CellResult] = {}
    parts: dict[int, dict[str, CellResult]] = {}
    queue: list[tuple[int, str]] = []
    for j, c in enumerate(cells):
        r = load_result(out_dir, c)
        if r is not None and r.status != STATUS_ERROR:
            results[j] = r
        elif c.na is not None or not split:
            queue.append((j, "all"))
        else:
            parts[j] = {}
            for p in PARTS:
                old = load_part(out_dir, c, p)
                if old is not None and old.status != STATUS_ERROR:
                    parts[j][p] = old
                else:
                    queue.append((j, p))
            if len(parts[j]) == len(PARTS):  # both parts were done; the merge was not
                results[j] = _finish_merge(cells[j], parts.pop(j), out_dir)
    group_of = getattr(ex, "group_of", None)
    if group_of is not None:  # e.g. one process per method configuration: its cells one after another
        first: dict = {}
        for j, _ in queue:
            first.setdefault(group_of(cells[j]), len(first))
        queue.sort(key=lambda t: first[group_of(cells[t[0]])])  # stable: the plan's order within a group
    bar = tqdm(total=len(cells), initial=len(results), desc="run", unit="cell", disable=None if progress else True)
    t_start = time.perf_counter()
    pending: dict[Any, tuple[int, str]] = {}
    attempts: dict[tuple[int, str], int] = {}
    solo: list[tuple[int, str]] = []  # tasks whose worker died: re-run one at a time

    def submit(t: tuple[int, str]) -> None:
        j, p = t
        attempts[t] = attempts.get(t, 0) + 1
        if p == "all":
            f = ex.submit(run_cell, cells[j], str(out_dir), progress=progress, context=context)
        elif p == "timing":
            f = ex.submit_timing(run_part, cells[j], p, str(out_dir), progress=False, context=context)
        else:
            f = ex.submit(run_part, cells[j], p, str(out_dir), progress=False, context=context)
        pending[f] = t

    def finished(t: tuple[int, str], r: CellResult) -> None:
        j, p = t
        if p == "all":
            results[j] = r
        else:
            parts[j][p] = r
            if len(parts[j]) < len(PARTS):
                return
            results[j] = _finish_merge(cells[j], parts.pop(j), out_dir)
        bar.set_postfix_str(f"{cells[j].method}/{cells[j].scene}/{cells[j].kind}: {results[j].status}")
        bar.update(1)
        if progress and bar.disable:  # not a terminal (cron, CI logs): one line per finished cell
            c = cells[j]
            print(f"[prtbench] {len(results)}/{len(cells)} {c.method}/{c.scene}/{c.kind}/b{c.bounces}: {results[j].status} "
                  f"({time.perf_counter() - t_start:.0f} s)", file=sys.stderr, flush=True)

    try:
        while queue or pending or solo:
            if solo:
                if not pending:
                    submit(solo.pop(0))
            else:
                n_timing = sum(1 for t in pending.values() if t[1] == "timing")
                for t in list(queue):
                    if len(pending) >= slots:
                        break
                    if t[1] == "timing" and timing_cap is not None and n_timing >= timing_cap:
                        continue
                    queue.remove(t)
                    if t[1] == "all" and cells[t[0]].na is not None:
                        finished(t, run_cell(cells[t[0]], out_dir))  # n/a: nothing to run
                        continue
                    submit(t)
                    n_timing += t[1] == "timing"
            if not pending:
                continue
            done = [f for f in pending if f.done()]
            if not done:
                if all(isinstance(f, Future) for f in pending):
                    done, _ = wait(list(pending), return_when=FIRST_COMPLETED)
                else:  # foreign futures: poll
                    time.sleep(0.05)
                    continue
            for f in done:
                t = pending.pop(f)
                try:
                    r = f.result()
                except Exception as e:  # the task did not return: its worker died / the pool broke
                    if attempts[t] <= RETRIES_AFTER_WORKER_LOSS:
                        solo.append(t)
                        continue
                    r = _lost(cells[t[0]], e, t[1])
                    atomic_write_json(result_path(out_dir, cells[t[0]]) if t[1] == "all"
                                      else part_path(out_dir, cells[t[0]], t[1]), r.to_dict())
                finished(t, r)
    finally:
        bar.close()
    return [results[j] for j in range(len(cells))]


def _finish_merge(cell: Cell, parts: dict[str, CellResult], out_dir: Path) -> CellResult:
    res = merge_parts(cell, parts["errors"], parts["timing"])
    atomic_write_json(result_path(out_dir, cell), res.to_dict())
    return res
