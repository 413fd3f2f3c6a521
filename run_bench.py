#!/usr/bin/env python3
"""prtbench command line.

  python run_bench.py run --suite smoke [--methods M …] [--scenes S …] [--scene-file F.toml]
                          [--out DIR] [--executor {local,processes,dask}] [--scheduler ADDRESS]
                          [--workers N] [--history PATH]
  python run_bench.py references --suite smoke          # pre-build the reference cache
  python run_bench.py compare RUN_A RUN_B               # changes between two runs, flagged (exit 1:
                                                        # regressions, 2: no cell in common)
  python run_bench.py study NAME [--out DIR] [--quick]  # a paper figure/table or a sweep
  python run_bench.py study terms-vs-exponent [--jobs N] [--scenes S,..] [--exponents 1,16,..] [--methods M,..]
                                              [--measure region|image]
  python run_bench.py study --list                      # every registered study
  python run_bench.py report RUN_DIR                    # rebuild a run's HTML report
  python run_bench.py list                              # scenes, methods, suites, kinds, studies
  python run_bench.py cache {info,prune,clear}          # the precompute cache (reports/precompute_cache.py)

A killed ``run`` resumes: run it again with the same ``--out`` and finished cells are skipped (failed
cells are redone). ``--executor processes`` runs cells in a spawn-based process pool, ``--executor
dask`` on an embedded Dask ``LocalCluster`` or, with ``--scheduler tcp://host:8786``, on an existing
Dask cluster (``reports/executors.py``; timings are taken one at a time per machine).
"""
from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path



# Spin iterations of libgomp's threads after a parallel region before they sleep (``GOMP_SPINCOUNT``) in
# the perf suite (`openmp_env`).
PERF_SPINCOUNT = 1_000_000


def openmp_env(argv: list[str]) -> dict[str, str]:
    """The OpenMP settings a run of ``argv`` takes where the user has not set them (`os.environ.setdefault`).

    ``OMP_WAIT_POLICY=PASSIVE`` for every run: OpenMP threads that spin while waiting turn a shared or
    oversubscribed machine's frame times into noise (measured: an in-out V frame 503 ms with the default
    policy vs 70 ms passive, 2 threads at load 8). With PASSIVE alone, though, each parallel region of a
    frame first wakes its sleeping threads: on a quiet 2-core host (session 39) a per-vertex triple
    product frame read V 3.9 / L 7.8 ms passive against 2.1 / 4.7 ms with a bounded spin
    (`benchmarks.tp_frames_ab --threads 2 --wall`). So ``--suite perf``, the run-time suite, run alone on
    the machine (README), also sets ``GOMP_SPINCOUNT`` (libgomp, which torch and the methods' C loops share;
    other runtimes ignore it): a thread spins that many iterations (milliseconds) after a region, then
    sleeps — across a frame's regions it is awake, across the harness's idle and G-buffer rasterisation
    (Dr.Jit's threads) it is not. ``OMP_WAIT_POLICY=ACTIVE`` (spin forever) was tried: a whole perf run
    2-5x slower, the spinning thread taking the rasteriser's core. The run records both (run.json, the
    report's header)."""
    suite = None
    for i, a in enumerate(argv):
        if a == "--suite" and i + 1 < len(argv):
            suite = argv[i + 1]
        elif a.startswith("--suite="):
            suite = a.split("=", 1)[1]
    env = {"OMP_WAIT_POLICY": "PASSIVE"}
    if suite == "perf":
        env["GOMP_SPINCOUNT"] = str(PERF_SPINCOUNT)
    return env


# set before torch loads its OpenMP runtime (spawned cell processes inherit them), and only where the
# user has not chosen
for _k, _v in openmp_env(sys.argv[1:]).items():
    os.environ.setdefault(_k, _v)


def _parser() -> argparse.ArgumentParser:
    from reports.suites import SUITES

    p = argparse.ArgumentParser(prog="prtbench", description="Benchmark precomputation-based relighting methods "
                                "against Mitsuba 3 references.")
    sub = p.add_subparsers(dest="cmd", required=True)

    def selection(sp):
        sp.add_argument("--suite", choices=sorted(SUITES), default="smoke")
        sp.add_argument("--methods", nargs="+", metavar="M", help="method names (default: all available)")
        sp.add_argument("--scenes", nargs="+", metavar="S", help="library scene names (default: the suite's)")
        sp.add_argument("--scene-file", action="append", default=[], metavar="F.toml",
                        help="a TOML scene file to run as well (repeatable)")
        # for tests / alternative installations: where scenes, references and metrics come from
        sp.add_argument("--backend", default="reports.backend", help=argparse.SUPPRESS)
        sp.add_argument("--plugin", action="append", default=[], help=argparse.SUPPRESS)

    r = sub.add_parser("run", help="run a benchmark suite and write its report")
    selection(r)
    r.add_argument("--out", type=Path, help="run directory (default out/<suite>); re-use it to resume")
    r.add_argument("--executor", choices=["local", "processes", "dask"], default="local",
                   help="where cells run: in this process (default), a spawn-based process pool, or Dask")
    r.add_argument("--scheduler", metavar="ADDRESS", default=None,
                   help="with --executor dask: an existing scheduler (tcp://host:8786) instead of a LocalCluster")
    r.add_argument("--workers", type=int, default=None, metavar="N",
                   help="processes / LocalCluster workers (default: one per core); with --scheduler: wait for N")
    r.add_argument("--history", type=Path, default=None, help="history parquet every run appends to "
                   "(default out/history.parquet)")
    r.add_argument("--no-history", action="store_true", help="do not read or append the history")
    iso = r.add_mutually_exclusive_group()
    iso.add_argument("--isolate", dest="isolate", action="store_true", default=None,
                     help="run every cell in a spawned child process (its own peak RSS)")
    iso.add_argument("--isolate-method", dest="isolate", action="store_const", const="method",
                     help="run each method configuration's cells in a spawned process of their own (the perf "
                          "suite's default: no cell is timed after another method's cells)")
    iso.add_argument("--no-isolate", dest="isolate", action="store_false", help="run cells in this process")
    r.add_argument("--fresh", action="store_true", help="start a new run in --out instead of resuming the one there")
    r.add_argument("--no-vertex-renders", action="store_true", help="skip the pyvista per-vertex error renders")
    r.add_argument("--quiet", action="store_true", help="no progress bars")
    r.add_argument("--strict", action="store_true", help="exit 1 when a cell is suspect (the sanity gate), "
                   "not only when one fails")
    r.add_argument("--device", default="cpu", help="torch device the methods render on: cpu (default) or cuda")
    r.add_argument("--ref-spp", type=int, default=None, metavar="N",
                   help="reference samples per pixel (default: the suite's); raise it when the noise floor hides "
                   "the differences between methods")
    r.add_argument("--frames", type=int, default=None, metavar="N",
                   help="frames per sequence (default: the suite's); frames past N are dropped from the scored ones")

    ref = sub.add_parser("references", help="pre-build the reference cache of a suite")
    selection(ref)
    ref.add_argument("--quiet", action="store_true")

    c = sub.add_parser("compare", help="compare two runs (run directories or results.parquet files)")
    c.add_argument("run_a", type=Path)
    c.add_argument("run_b", type=Path)
    c.add_argument("--all", action="store_true", help="list unchanged values too")

    s = sub.add_parser("study", help="run a paper figure/table or a sweep (methods/<m>/study.py, reports/studies.py)")
    s.add_argument("name", nargs="?")
    s.add_argument("--list", action="store_true", help="list every registered study and exit")
    s.add_argument("--out", type=Path, default=None, help="output folder (default out/studies/<name>)")
    s.add_argument("--quick", action="store_true", help="a small, fast version")
    s.add_argument("--jobs", type=int, default=None,
                   help="terms-vs-exponent: worker processes, one torch thread each (default: cores, at most 2; "
                        "1 = in this process); the numbers do not depend on it")
    s.add_argument("--scenes", default=None,
                   help="terms-vs-exponent: comma-separated scenes of the study (default: all), for reduced runs")
    s.add_argument("--exponents", default=None,
                   help="terms-vs-exponent: comma-separated Phong exponents (default: 1,2,...,256)")
    s.add_argument("--methods", default=None,
                   help="terms-vs-exponent: comma-separated term ladders (default: every registered one)")
    s.add_argument("--measure", choices=("region", "image"), default=None,
                   help="terms-vs-exponent: the pixels the searched error is taken over: the varied (glossy) region's "
                        "(default) or the whole image's (the study before session 47)")

    ls = sub.add_parser("list", help="what can be run: scenes, methods, suites, sequence kinds, studies")
    ls.add_argument("--test-only", action="store_true", help="vertex counts at test size only (faster)")

    rep = sub.add_parser("report", help="rebuild the HTML report of a run directory")
    rep.add_argument("run_dir", type=Path)
    rep.add_argument("--history", type=Path, default=None)

    ca = sub.add_parser("cache", help="inspect, prune or clear the precompute cache")
    ca.add_argument("action", choices=["info", "prune", "clear"])
    ca.add_argument("--max-gb", type=float, default=None,
                    help="prune to this size (default $PRTBENCH_CACHE_MAX_GB, else 20)")
    return p


def _scenes(args) -> list[str] | None:
    """The scene selection; an unknown library scene or a missing or bad scene file is a ValueError
    (one line naming the file and key, like an unknown method) before anything is written."""
    from reports.backend import load_backend

    be = load_backend(args.backend)
    known = list(be.scene_names()) if hasattr(be, "scene_names") else None
    for n in args.scenes or []:
        if known is not None and n not in known and not n.startswith("file:"):
            raise ValueError(f"unknown scene {n!r}; available: {', '.join(known)}")
    for f in args.scene_file:
        if not Path(f).is_file():
            raise ValueError(f"{f}: scene file not found")
        be.get_scene(f"file:{Path(f).resolve()}", "test")  # load it once: its errors before --fresh clears anything
    names = list(args.scenes or [])
    names += [f"file:{Path(f).resolve()}" for f in args.scene_file]
    if args.scene_file and not args.scenes:
        return names  # only the scene files
    return names or None


def cmd_run(args) -> int:
    from reports.executors import make_executor
    from reports.pipeline import run_suite
    from reports.store import DEFAULT_HISTORY
    from reports.suites import get_suite

    from reports.pipeline import read_run_json

    suite = _overridden(get_suite(args.suite), args)
    scenes = _scenes(args)
    out = args.out or Path("out") / suite.name
    history = None if args.no_history else (args.history or DEFAULT_HISTORY)
    if args.fresh:
        from reports.pipeline import clear_run

        clear_run(out)
    elif (old := read_run_json(out)) is not None:
        print(f"resuming run {old['run_id']} in {out} (git {old['git_sha'][:12]}) unless it cannot be (then it is "
              f"moved aside): finished cells are kept, this selection is added; --fresh starts a new one",
              file=sys.stderr)
    executor = make_executor(args.executor, workers=args.workers, scheduler=args.scheduler)
    try:
        if not args.quiet:
            print(f"executor: {executor.describe()}", file=sys.stderr)
        res = run_suite(suite, out, methods=args.methods, scenes=scenes, executor=executor,
                        history=history, backend=args.backend, plugins=tuple(args.plugin), isolate=args.isolate,
                        progress=not args.quiet, vertex_renders=not args.no_vertex_renders, device=args.device)
    finally:
        executor.shutdown()
    print(f"run {res.run_id}: {res.n_ok} cells ok, {res.n_suspect} suspect, {res.n_na} n/a, {res.n_error} failed"
          + (f"; wall time {res.wall_time}" if res.wall_time else ""))
    if res.changes is not None:
        from reports.regress import baseline_runs, cells_compared, flagged, format_changes

        fl = flagged(res.changes)
        if len(fl):
            print(format_changes(res.changes, only_flagged=True))
        if not (fl["flag"] == "regression").any():
            print("no regressions since the last run")
        print(f"compared {cells_compared(res.changes)} cell(s), each with its most recent earlier run: "
              f"{baseline_runs(res.changes)}")
    elif history is not None:
        print("no earlier run in the history has any of these cells: nothing compared")
    print(f"results: {res.table.resolve()}")
    if res.history:
        print(f"history: {res.history.resolve()}")
    print(f"report:  {res.report.resolve()}")
    if res.n_suspect:
        print(f"{res.n_suspect} suspect cell(s): the sanity gate found a plainly wrong image (listed above and in "
              f"the report){'' if args.strict else '; --strict makes this fail the run'}")
    return 0 if res.n_error == 0 and not (args.strict and res.n_suspect) else 1


def _overridden(suite, args):
    """The suite with --ref-spp / --frames / --device applied (validated here: one clear error)."""
    import dataclasses

    import torch

    if args.device not in ("cpu", "cuda") and not str(args.device).startswith("cuda:"):
        raise ValueError(f"--device must be cpu or cuda[:N], got {args.device!r}")
    if str(args.device).startswith("cuda") and not torch.cuda.is_available():
        raise ValueError(f"--device {args.device}: torch sees no CUDA device on this machine")
    changes = {}
    if args.ref_spp is not None:
        if args.ref_spp < 2 or args.ref_spp % 2:
            raise ValueError(f"--ref-spp must be an even number >= 2 (references are two halves), got {args.ref_spp}")
        changes["ref_spp"] = args.ref_spp
        changes["eq_err_spp"] = tuple(sorted({min(s, args.ref_spp) for s in suite.eq_err_spp} | {args.ref_spp})) \
            if suite.eq_err_spp else ()
    if args.frames is not None:
        if args.frames < 1:
            raise ValueError(f"--frames must be >= 1, got {args.frames}")
        changes["n_frames"] = args.frames
        changes["score_frames"] = tuple(f for f in suite.score_frames if f < args.frames)
    return dataclasses.replace(suite, **changes) if changes else suite


def cmd_references(args) -> int:
    from reports.pipeline import build_references
    from reports.suites import get_suite

    n = build_references(get_suite(args.suite), methods=args.methods, scenes=_scenes(args), backend=args.backend,
                         plugins=tuple(args.plugin), progress=not args.quiet)
    print(f"{n} references ready in the cache")
    return 0


def cmd_compare(args) -> int:
    from reports.regress import NoCommonCells, cells_compared, compare_runs, flagged, format_changes
    from reports.store import read_table

    a, b = read_table(args.run_a), read_table(args.run_b)
    print(f"{a['run_id'].iloc[0] if len(a) else args.run_a}  →  {b['run_id'].iloc[0] if len(b) else args.run_b}")
    try:
        ch = compare_runs(a, b, require_common=True)
    except NoCommonCells as e:
        print(f"prtbench: compare: {e} ({args.run_a} vs {args.run_b})", file=sys.stderr)
        return 2
    print(format_changes(ch, only_flagged=not args.all))
    if len(ch) == 0:
        print("the shared cells did not finish ok in both runs: no values compared")
    else:
        print(f"{cells_compared(ch)} cell(s) compared")
    return 1 if (len(ch) and (flagged(ch)["flag"] == "regression").any()) else 0


def cmd_study(args) -> int:
    from reports import studies

    if args.list or args.name is None:
        for name, st in sorted(studies.STUDIES.items()):
            print(f"{name:28s} {st.paper or 'cross-method':20s} {st.description}")
        return 0 if args.list else 2
    if args.name not in studies.STUDIES:
        print(f"unknown study {args.name!r}; available: {', '.join(sorted(studies.STUDIES))}", file=sys.stderr)
        return 2
    out = args.out or Path("out") / "studies" / args.name
    options: dict = {}
    if args.jobs is not None:
        options["jobs"] = args.jobs
    for key in ("scenes", "methods"):
        if getattr(args, key) is not None:
            options[key] = [x.strip() for x in getattr(args, key).split(",") if x.strip()]
    if args.measure is not None:
        options["measure"] = args.measure
    if args.exponents is not None:
        try:
            options["exponents"] = [float(x) for x in args.exponents.split(",") if x.strip()]
        except ValueError:
            print(f"--exponents must be comma-separated numbers, got {args.exponents!r}", file=sys.stderr)
            return 2
    try:
        paths = studies.run_study(args.name, out, quick=args.quick, **options)
    except ValueError as e:
        if not options:
            raise
        print(f"study {args.name}: {e}", file=sys.stderr)
        return 2
    for p in paths:
        print(p)
    return 0


def cmd_report(args) -> int:
    import json

    from reports import regress, store
    from reports.html import build_report
    from reports.pipeline import read_run_json

    df = store.read_table(args.run_dir)
    meta = read_run_json(args.run_dir) or {}
    changes = prev_id = None
    hist_path = args.history or store.DEFAULT_HISTORY
    if Path(hist_path).exists() and len(df):
        changes = regress.compare_with_history(store.read_history(hist_path), df)
        prev_id = regress.baseline_runs(changes)
        changes = changes if prev_id is not None else None
    if (args.run_dir / "provenance.json").exists():
        meta["provenance"] = json.loads((args.run_dir / "provenance.json").read_text())
    p = build_report(df, args.run_dir / "report.html", run_dir=args.run_dir, meta=meta, changes=changes, prev_run=prev_id)
    print(f"report:  {p.resolve()}")
    return 0


def cmd_list(args) -> int:
    from reports import studies  # noqa: F401  (registers the cross-method studies too)
    from reports.listing import catalogue

    print(catalogue(sizes=("test",) if args.test_only else ("test", "bench")))
    return 0


def cmd_cache(args) -> int:
    from reports import precompute_cache as pc

    def gb(n: int) -> str:
        return f"{n / 1e9:.3f} GB"

    if args.action == "clear":
        r = pc.clear()
        print(f"cleared {pc.cache_folder()}: {r['files']} files, {gb(r['freed'])}")
    elif args.action == "prune":
        if args.max_gb is not None and not (0 <= args.max_gb < float("inf")):
            raise ValueError(f"--max-gb must be a number of GB >= 0, got {args.max_gb}")
        r = pc.prune(None if args.max_gb is None else int(args.max_gb * 1e9))
        print(f"pruned {pc.cache_folder()}: {r['removed']} entries and {r['files']} other files removed "
              f"({gb(r['freed'])}), {gb(r['bytes'])} left")
    else:
        i = pc.info()
        print(f"precompute cache {i['folder']}: {i['entries']} entries, {gb(i['bytes'])} "
              f"(cap {gb(i['max_bytes'])}, ${pc.ENV_MAX_GB})")
        for name, d in sorted(i["per_method"].items()):
            print(f"  {name}: {d['entries']} entries, {gb(d['bytes'])}")
        if i["other_files"]:
            print(f"  not entries (removed by prune): {i['other_files']} files, {gb(i['other_bytes'])}")
    return 0


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    try:
        return {"run": cmd_run, "references": cmd_references, "compare": cmd_compare, "study": cmd_study,
                "report": cmd_report, "list": cmd_list,
                "cache": cmd_cache}[args.cmd](args)
    except (ValueError, FileNotFoundError) as e:
        print(f"prtbench: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
