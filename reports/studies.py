"""Cross-method studies (``run_bench.py study NAME``); paper figures and tables live beside their
methods (``methods/<m>/study.py``) and register in ``methods.studies``.

``terms-vs-exponent`` — one yardstick for every method (`terms_vs_exponent`): on the same scenes
(sphere_plane: a glossy sphere shadowing a plane; shadow_detail: a glossy object shadowing
itself), with the glossy object's material made Phong of exponent s (its kd, ks kept), for s = 1,
2, 4, ..., 256, find on each registered term ladder (`methods.studies.register_term_ladder`) the
smallest configuration whose rendered image reaches a relative RMSE (RMSE / mean reference
radiance, over the pixels every sub-sample of which sees the varied region: ``measure="region"``,
`MEASURES`) of 5 % and of 10 % against a converged Mitsuba reference of the same frame (direct
lighting, ``ref_spp`` samples per pixel, cached on disk); record the term count and
the run-time bytes per vertex (``sum(method.memory()) / vertices``). The ladder is bisected, or
scanned rung by rung where its error can grow along it (``TermLadder.scan``: the SH ladders); renders
are cached per (method, rung, s) within a run. Targets are searched loosest first, the tighter one
starting at the looser one's rung (a rung that reaches the tighter target reaches the looser one).
Outputs (in ``out_dir``):

* ``terms_vs_exponent.png`` — terms (top) and bytes per vertex (bottom) vs s, one column per
  scene, one colour per method (`reports.palette`), solid 5 %, dashed 10 %; an open marker = not
  reached (plotted at the largest rung tried);
* ``terms_vs_exponent.csv`` — every plotted number, one row per (scene, method, s, target): the
  kept rung, its terms and bytes, its error (``rel_rmse``, searched; ``rel_rmse_image``, the whole
  image's), the rung below (the ladder step) and its error, the noise floor of the reference over
  the searched pixels and over the image, ``monotone`` (False: fewer terms than at a smaller s, or reached
  after a smaller s was not) and a note saying why, ``search`` (``bisect`` or ``scan``);
* ``ladder_evaluations.csv`` — every render the search made (scene, method, s, rung, error,
  bytes, seconds); ``summary.json`` — settings, floors, seconds per method.

Speed (the numbers are not affected): the (scene, method) searches run in ``jobs`` worker
processes (the CLI: cores, at most 2; `yardstick_table`), and the precomputes of one search share
the pieces that depend on neither the rung nor the exponent (`methods.base.shared_precompute`),
so a render's ``seconds`` count only what it computed. ``--scenes/--exponents/--methods`` run a
reduced study (`restrict`).

``terms-own-criteria`` — each method's terms-vs-exponent contributor
(`methods.studies.register_terms_contributor`) under its own criterion (not comparable across
methods: that is what ``terms-vs-exponent`` is for) → ``terms_by_method.csv/png``, and Mahajan
2008 Fig. 3B/C / 6's rendered error vs K of every ``register_error_vs_terms`` function →
``error_vs_terms.csv``. Mahajan 2008's analysis figures (Figs. 2, 3A, 5, 7C) are the studies
``mahajan-fig2-5``, ``mahajan-fig3a``, ``mahajan-fig7c``. The in-out contributor's K is counted in
the BRDF's own norm (Fig. 3A: 99 % of the hemisphere BRDF-matrix energy, 40 × 40 grid); the
renderer chooses its K in the cosine-weighted norm (methods/inout) — and ``terms-vs-exponent``
measures what the rendered image needs, which no energy criterion does.
"""
from __future__ import annotations

import contextlib
import copy
import dataclasses
import json
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Sequence

import methods.registry  # noqa: F401  (loads every method's study registrations)
from methods.base import shared_precompute
from methods.inout import study as mahajan
from methods.studies import (ERROR_VS_TERMS, STUDIES, TERM_LADDERS, TERMS_CONTRIBUTORS, Study,  # noqa: F401
                             TermLadder, pyplot, register_study, run_study, save_fig, terms_table)  # (STUDIES, run_study: the CLI's)
from reports.palette import method_color

# -- terms-vs-exponent: one yardstick ---------------------------------------------------------


@dataclass(frozen=True)
class YardstickConfig:
    """Sweep of `terms_vs_exponent`.

    scenes: (scene name, region whose material becomes Phong(kd, ks of the scene, s)); size: scene
    size; exponents: Phong s; targets: relative RMSE targets; ref_spp: reference samples per pixel
    (direct lighting; its noise floor is in the CSV); spp_side: G-buffer sub-samples per pixel
    side; methods: ladder names (None = every registered one); quick: use each ladder's quick rungs;
    measure: the pixels the searched error is taken over (`MEASURES`): "region" — those every
    sub-sample of which sees the varied region (the default), "image" — every covered pixel (the
    study before session 47). Both errors are in the CSVs whichever is searched.
    """

    scenes: tuple[tuple[str, str], ...] = (("sphere_plane", "sphere"), ("shadow_detail", "object"))
    size: str = "test"
    exponents: tuple[float, ...] = (1, 2, 4, 8, 16, 32, 64, 128, 256)
    targets: tuple[float, ...] = (0.05, 0.10)
    ref_spp: int = 16384
    spp_side: int = 2
    methods: tuple[str, ...] | None = None
    quick: bool = False
    measure: str = "region"

    def __post_init__(self) -> None:
        if not self.scenes or not self.exponents or not self.targets:
            raise ValueError("scenes, exponents and targets must be non-empty")
        if self.measure not in MEASURES:
            raise ValueError(f"measure must be one of {MEASURES}, got {self.measure!r}")
        if any(not (isinstance(s, (int, float)) and math.isfinite(s) and s > 0) for s in self.exponents):
            raise ValueError(f"exponents must be finite numbers > 0, got {self.exponents}")
        if any(not 0 < t < 1 for t in self.targets):
            raise ValueError(f"targets must be in (0, 1), got {self.targets}")
        if isinstance(self.ref_spp, bool) or not isinstance(self.ref_spp, int) or self.ref_spp < 2 or self.ref_spp % 2:
            raise ValueError(f"ref_spp must be an even int >= 2, got {self.ref_spp!r}")


# What the searched relative RMSE is taken over. The ladders vary the terms of the varied region only (every other
# region keeps its method's rule), so error elsewhere is the same at every rung and every s: measured over the whole
# image, the ground's per-vertex shadows at test size (sphere_plane s = 1: 94-95 % of in-out's (K = 256) and SH PRT's
# (order 10) squared error on the plane, 8.4 / 7.5 % relative there, the sphere at 2.3 / 2.4 %;
# `benchmarks.yardstick_split`) set a floor no rung can cross: the study measured the ground instead of the terms.
MEASURES = ("region", "image")

YARDSTICK = YardstickConfig()
# --quick: one scene, two exponents, each ladder's two cheap rungs, a noisy reference (64 spp: floor
# over the sphere's pixels 10.5 / 17.3 % at s = 1 / 16, over the image 8.4 / 9.9 %) and targets above it (tests;
# tens of seconds).
YARDSTICK_QUICK = YardstickConfig(scenes=(("sphere_plane", "sphere"),), exponents=(1, 16), targets=(0.25, 0.5),
                                 ref_spp=64, quick=True)


@dataclass
class _Frame:
    """One (scene, s): the Phong-s scene, its frame, G-buffer, reference, mask and its statistics."""

    scene: Any
    frame: Any
    gbuffer: Any
    reference: Any
    mask: Any            # the pixels the searched error is taken over (``cfg.measure``)
    mean: float          # the reference's mean radiance over them
    floor: float         # the reference's own relative RMSE over them
    vertices: int
    image_mask: Any = None   # every covered pixel, its mean and floor (None: the same as mask, mean, floor)
    image_mean: float | None = None
    image_floor: float | None = None


def region_pixels(gbuffer, scene, region: str, covered) -> Any:
    """(H, W) bool: the covered pixels every G-buffer sub-sample of which hits ``region`` (no silhouette pixel
    that mixes it with what lies behind). ``ValueError`` when the scene has no such region or no such pixel."""
    import torch

    names = list(scene.regions)
    if region not in names:
        raise ValueError(f"scene has no region {region!r}; regions: {names}")
    own = ((gbuffer.region == names.index(region)) & gbuffer.hit).to(torch.float32)
    frac = gbuffer.resolve(own[:, None].expand(-1, 3).contiguous())[..., 0]
    m = torch.as_tensor(covered, dtype=torch.bool) & (frac == 1.0)
    if not bool(m.any()):
        raise ValueError(f"no pixel of the frame is covered by region {region!r} alone")
    return m


def _phong_frame(scene_name: str, region: str, s: float, cfg: YardstickConfig) -> _Frame:
    from references.metrics import rmse
    from references.setup import frame_setup
    from scenes.library import get_scene
    from scenes.materials import Phong
    from scenes.sequences import make_sequence

    base = get_scene(scene_name, cfg.size)
    if region not in base.materials:
        raise ValueError(f"scene {scene_name!r} has no region {region!r}; regions: {sorted(base.materials)}")
    old = base.materials[region]
    mats = dict(base.materials)
    mats[region] = Phong(kd=old.kd, ks=old.ks, s=float(s))
    scene = dataclasses.replace(base, materials=mats)
    frame = dataclasses.replace(make_sequence(scene, "V", n_frames=1, seed=0)[0], materials=mats)
    su = frame_setup(scene, frames=[frame], spp_side=cfg.spp_side, ref_spp=cfg.ref_spp, bounces=(0,), seed=0)
    ref, mask = su.references[0], su.mask(0)
    mean = float(ref.image[mask].mean())
    floor = rmse(ref.half_a, ref.half_b, mask) / 2 / mean  # the full image's own relative RMSE
    nv = int(scene.geometry().V.shape[0])
    if cfg.measure == "image":
        return _Frame(scene, frame, su.gbuffer, ref, mask, mean, floor, nv)
    rm = region_pixels(su.gbuffer, scene, region, mask)
    rmean = float(ref.image[rm].mean())
    rfloor = rmse(ref.half_a, ref.half_b, rm) / 2 / rmean
    return _Frame(scene, frame, su.gbuffer, ref, rm, rmean, rfloor, nv, mask, mean, floor)


class _Evaluator:
    """Renders rung i of a ladder at (scene, s) once per run; keeps one precompute per rung of a
    ``material_at_render`` ladder (per scene) and renders a copy of it per exponent; shares the
    pieces of the precomputes that depend on neither (``memo``)."""

    def __init__(self, ladder: TermLadder, rungs: tuple[dict, ...], scene_name: str, region: str,
                 shared: bool = True):
        self.ladder, self.rungs, self.scene_name, self.region = ladder, rungs, scene_name, region
        self.shared = shared
        self.cache: dict[tuple[int, float], dict] = {}
        self._pre: dict[int, Any] = {}
        # rung- and exponent-independent precompute pieces shared by this search's precomputes
        # (`methods.base.shared_precompute`: the same objects, so the same numbers; the in-out
        # regions the ladder does not vary, PTT's lobe visibility tables and env filters, PTT's lobe
        # fit per exponent, triple product's visibility and BRDF tables before truncation); a
        # render's seconds count only what it computed
        self.memo: dict = {}

    def __call__(self, i: int, s: float, fr: _Frame) -> dict:
        from references.metrics import rmse

        key = (i, float(s))
        if key in self.cache:
            return self.cache[key]
        cfg = self.rungs[i]
        t0, c0 = time.perf_counter(), time.process_time()
        if self.ladder.material_at_render:
            if i not in self._pre:
                m = self.ladder.make(dict(cfg), self.region)
                with shared_precompute(self.memo) if self.shared else contextlib.nullcontext():
                    m.precompute(fr.scene)
                self._pre[i] = m
            # a fresh copy per exponent: run-time caches of one exponent (e.g. zh_shadow's M^α) are
            # neither reused nor counted in another exponent's memory
            m = copy.deepcopy(self._pre[i])
        else:
            m = self.ladder.make(dict(cfg), self.region)
            with shared_precompute(self.memo) if self.shared else contextlib.nullcontext():
                m.precompute(fr.scene)
        img = m.render(fr.frame, fr.gbuffer)
        err = rmse(img, fr.reference.image, fr.mask) / fr.mean
        err_image = err if fr.image_mask is None else rmse(img, fr.reference.image, fr.image_mask) / fr.image_mean
        mem = int(sum(m.memory().values()))
        rec = {"scene": self.scene_name, "method": self.ladder.method, "exponent": float(s), "rung": i,
               "terms": int(self.ladder.terms_of(cfg)), "config": json.dumps(cfg, sort_keys=True),
               "rel_rmse": float(err), "rel_rmse_image": float(err_image),
               "bytes_per_vertex": mem / fr.vertices, "memory_bytes": mem,
               "seconds": time.perf_counter() - t0, "cpu_seconds": time.process_time() - c0}
        self.cache[key] = rec
        return rec


def _first_below(ev: _Evaluator, s: float, fr: _Frame, t: float, lo: int, hint: int) -> int | None:
    """Smallest rung i in [lo, top] with rel_rmse <= t (None: none of them): for a ``scan`` ladder
    the rungs in order from ``lo``; else, assuming the error does not grow along the ladder, gallop
    up from ``hint`` (the same target's rung at the previous s), then bisect — a few renders when
    the answer moves by a rung or two."""
    top = len(ev.rungs) - 1

    def ok(i: int) -> bool:
        e = ev(i, s, fr)["rel_rmse"]
        return math.isfinite(e) and e <= t

    if ev.ladder.scan:
        return next((i for i in range(lo, top + 1) if ok(i)), None)

    h = min(max(hint, lo), top)
    step = 1
    if ok(h):  # gallop down: b reaches t, a misses it (or is below lo)
        b = h
        while True:
            cand = b - step
            if cand < lo:
                a = lo - 1
                break
            if not ok(cand):
                a = cand
                break
            b, step = cand, 2 * step
    else:  # gallop up
        a = h
        while True:
            if a == top:
                return None
            cand = min(a + step, top)
            if ok(cand):
                b = cand
                break
            a, step = cand, 2 * step
    while b - a > 1:  # err(a) > t >= err(b)
        mid = (a + b) // 2
        if ok(mid):
            b = mid
        else:
            a = mid
    return b


def _search(ev: _Evaluator, s: float, fr: _Frame, targets: tuple[float, ...],
            hints: dict[float, int]) -> dict[float, dict]:
    """Per target: the smallest rung reaching it (`_first_below`), its record, the rung below's
    record if rendered; loosest target first, the tighter one searched from its rung up."""
    top = len(ev.rungs) - 1
    lo = 0
    out: dict[float, dict] = {}
    for t in sorted(targets, reverse=True):
        i = None if lo > top else _first_below(ev, s, fr, t, lo, hints.get(t, lo))
        if i is None:
            k = ev(top, s, fr)
            out[t] = {"reached": False, "kept": k, "below": None}
            lo = top + 1
            continue
        below = ev.cache.get((i - 1, float(s))) if i > 0 else None
        out[t] = {"reached": True, "kept": ev(i, s, fr), "below": below}
        hints[t] = i
        lo = i
    return out


def _flag_monotone(rows: list[dict]) -> None:
    """Set ``monotone`` / ``note`` of rows of one (scene, method, target), in increasing s."""
    best: dict | None = None  # the row with the most terms so far (reached)
    failed_at: float | None = None
    for r in rows:
        r["monotone"], r["note"] = True, ""
        if not r["reached"]:
            failed_at = r["exponent"] if failed_at is None else failed_at
            continue
        if failed_at is not None:
            r["monotone"] = False
            r["note"] = (f"reached although s={failed_at:g} was not (errors near the target: "
                         f"{r['rel_rmse']:.4f} here)")
        elif best is not None and r["terms"] < best["terms"]:
            r["monotone"] = False
            below = f"{r['prev_rel_rmse']:.4f}" if r["prev_rel_rmse"] != "" else "not rendered"
            r["note"] = (f"{r['terms']} terms < {best['terms']} at s={best['exponent']:g}: kept rung error "
                         f"{r['rel_rmse']:.4f}, rung below {below}, at s={best['exponent']:g} "
                         f"{best['rel_rmse']:.4f} (one ladder step; the error curves cross near the target)")
        if best is None or r["terms"] >= best["terms"]:
            best = r


def _search_one(scene_name: str, region: str, name: str, frames: dict[float, _Frame], cfg: YardstickConfig,
                on_exponent=None, shared: bool = True) -> tuple[list[dict], list[dict]]:
    """The search of one (scene, method) over every exponent, in increasing s (the hints carry from
    one s to the next, so a (scene, method) is one sequential unit) → (figure rows, evaluations)."""
    lad = TERM_LADDERS[name]
    rungs = lad.quick if cfg.quick else lad.ladder
    ev = _Evaluator(lad, rungs, scene_name, region, shared)
    mrows: dict[float, list[dict]] = {t: [] for t in cfg.targets}
    hints: dict[float, int] = {}
    for s, fr in frames.items():
        found = _search(ev, s, fr, tuple(cfg.targets), hints)
        for t in cfg.targets:
            f = found[t]
            k, b = f["kept"], f["below"]
            row = {"scene": scene_name, "vertices": fr.vertices, "method": name,
                   "term_name": lad.term_name, "exponent": s, "target": t, "reached": f["reached"],
                   "terms": k["terms"], "bytes_per_vertex": k["bytes_per_vertex"],
                   "rel_rmse": k["rel_rmse"], "rel_rmse_image": k["rel_rmse_image"], "measure": cfg.measure,
                   "pixels": int(fr.mask.sum()), "config": k["config"], "rung": k["rung"],
                   "ladder_len": len(rungs),
                   "prev_terms": b["terms"] if b else ("" if k["rung"] == 0 or not f["reached"]
                                                       else lad.terms_of(rungs[k["rung"] - 1])),
                   "prev_rel_rmse": b["rel_rmse"] if b else "",
                   "top_terms": lad.terms_of(rungs[-1]),
                   "top_rel_rmse": ev.cache[(len(rungs) - 1, s)]["rel_rmse"]
                   if (len(rungs) - 1, s) in ev.cache else "",
                   "noise_floor": fr.floor, "noise_floor_image": fr.floor if fr.image_floor is None else fr.image_floor,
                   "ref_spp": cfg.ref_spp}
            row["ladder_step"] = (row["terms"] / row["prev_terms"]) if row["prev_terms"] not in ("", 0) else ""
            row["search"] = "scan" if lad.scan else "bisect"
            mrows[t].append(row)
        if on_exponent is not None:
            on_exponent()
    rows: list[dict] = []
    for t in cfg.targets:
        _flag_monotone(mrows[t])
        rows += mrows[t]
    return rows, sorted(ev.cache.values(), key=lambda r: (r["exponent"], r["rung"]))


# -- parallel searches (``jobs`` > 1) ----------------------------------------------------------
# Each (scene, method) search is independent of the others, so ``jobs`` worker processes (spawned:
# fresh interpreters, one torch thread each unless told) run them; the parent renders the frames and
# references once and sends them. Every search is the sequential one of the plain path and the
# methods' numbers do not depend on the thread count (``methods.core.threads``), so the rows are the
# plain path's (tests/reports/test_yardstick.py; zh_shadow's SH order 3, whose 9-row float32 product
# rounded differently with 1 and 2 threads, now runs it on one thread: `methods.zh_shadow.runtime.
# world_visibility`, tests/methods/test_threads.py). One thread per worker, because
# two processes of two threads on two busy cores spend much of their CPU time in OpenMP waits. Only
# ladders registered at import (``methods.registry``) exist in a worker; the workers are handed the
# most expensive searches first (a scheduling hint only).
SEARCH_COST_HINT = {"ptt": 4.0, "inout": 3.5, "triple_product": 2.0}
_WORKER_QUEUE = None


def default_jobs() -> int:
    """Worker processes of the CLI's run: the machine's cores, at most 2 (the 2-core bench machine)."""
    import os

    return max(1, min(2, os.cpu_count() or 1))


def _worker_init(queue, threads: int) -> None:
    import torch

    global _WORKER_QUEUE
    torch.set_num_threads(threads)
    _WORKER_QUEUE = queue


def _worker_tick() -> None:
    if _WORKER_QUEUE is not None:
        _WORKER_QUEUE.put(1)


def _worker_search(scene_name: str, region: str, name: str, frames: dict[float, _Frame],
                   cfg: YardstickConfig, shared: bool) -> tuple[list[dict], list[dict], float]:
    t0 = time.perf_counter()
    rows, evals = _search_one(scene_name, region, name, frames, cfg, on_exponent=_worker_tick, shared=shared)
    return rows, evals, time.perf_counter() - t0


def _run_parallel(jobs: int, units: list[tuple[str, str, str]], frames: dict[str, dict[float, _Frame]],
                  cfg: YardstickConfig, bar, threads: int, shared: bool) -> dict[tuple[str, str], tuple[list[dict], list[dict]]]:
    import multiprocessing as mp
    import queue as queue_
    import sys
    from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait

    ctx = mp.get_context("spawn")
    q = ctx.Queue()
    order = sorted(units, key=lambda u: -SEARCH_COST_HINT.get(u[2], 1.0))  # stable: ties keep their order
    out: dict[tuple[str, str], tuple[list[dict], list[dict]]] = {}

    def drain() -> None:
        while True:
            try:
                bar.update(q.get_nowait())
            except queue_.Empty:
                return

    with ProcessPoolExecutor(max_workers=jobs, mp_context=ctx, initializer=_worker_init, initargs=(q, threads)) as ex:
        todo = {ex.submit(_worker_search, sc, reg, name, frames[sc], cfg, shared): (sc, name) for sc, reg, name in order}
        while todo:
            done, _ = wait(todo, timeout=0.5, return_when=FIRST_COMPLETED)
            drain()
            for f in done:
                sc, name = todo.pop(f)
                rows, evals, secs = f.result()
                out[(sc, name)] = (rows, evals)
                print(f"terms-vs-exponent: {sc} / {name} done ({len(evals)} renders, {secs:.0f} s)",
                      file=sys.stderr, flush=True)
    drain()
    return out


def _floors(frames: dict[float, _Frame]) -> dict[str, float]:
    """The reference's own relative RMSE per exponent over the searched pixels (``"s"``) and, when those are the
    varied region's, over the whole image (``"s/image"``)."""
    out: dict[str, float] = {}
    for s, fr in frames.items():
        out[f"{s:g}"] = fr.floor
        if fr.image_floor is not None:
            out[f"{s:g}/image"] = fr.image_floor
    return out


def yardstick_table(cfg: YardstickConfig = YARDSTICK, *, progress=None, jobs: int = 1,
                    worker_threads: int | None = None, shared: bool = True) -> tuple[list[dict], list[dict], dict]:
    """Run the search (module docstring) → (figure rows, every evaluation, per-(scene, s) floors).

    jobs: 1 = every search in this process (any registered ladder); > 1 = that many worker
    processes (ladders registered at import only; the same rows, see the comment above
    `SEARCH_COST_HINT`) with ``worker_threads`` torch
    threads each (default 1).
    shared: share rung-independent precompute pieces within a search (`_Evaluator`); False
    precomputes every rung from scratch (the oracle of the shared path)."""
    names = sorted(TERM_LADDERS) if cfg.methods is None else list(cfg.methods)
    for n in names:
        if n not in TERM_LADDERS:
            raise ValueError(f"no term ladder registered for {n!r}; registered: {sorted(TERM_LADDERS)}")
    if isinstance(jobs, bool) or not isinstance(jobs, int) or jobs < 1:
        raise ValueError(f"jobs must be an int >= 1, got {jobs!r}")
    bar = progress or mahajan._NoBar()
    rows: list[dict] = []
    evals: list[dict] = []
    floors: dict[str, dict] = {}
    if jobs == 1:
        for scene_name, region in cfg.scenes:
            frames = {float(s): _phong_frame(scene_name, region, float(s), cfg) for s in cfg.exponents}
            floors[scene_name] = _floors(frames)
            for name in names:
                r, e = _search_one(scene_name, region, name, frames, cfg, on_exponent=lambda: bar.update(1),
                                   shared=shared)
                rows += r
                evals += e
        return rows, evals, floors
    all_frames: dict[str, dict[float, _Frame]] = {}
    for scene_name, region in cfg.scenes:
        all_frames[scene_name] = {float(s): _phong_frame(scene_name, region, float(s), cfg) for s in cfg.exponents}
        floors[scene_name] = _floors(all_frames[scene_name])
    units = [(sc, reg, name) for sc, reg in cfg.scenes for name in names]
    threads = 1 if worker_threads is None else int(worker_threads)
    done = _run_parallel(min(jobs, len(units)), units, all_frames, cfg, bar, threads, shared)
    for sc, _reg, name in units:  # the plain path's order
        r, e = done[(sc, name)]
        rows += r
        evals += e
    return rows, evals, floors


def plot_yardstick(rows: list[dict], path: Path, *, ref_spp: int, measure: str = "region") -> Path:
    """terms (top row) and bytes per vertex (bottom row) vs s, one column per scene (module
    docstring); legend outside the axes."""
    from matplotlib.lines import Line2D

    plt = pyplot()
    scenes = list(dict.fromkeys(r["scene"] for r in rows))
    methods_ = list(dict.fromkeys(r["method"] for r in rows))
    targets = sorted({r["target"] for r in rows})
    style = {t: ("-", "--", ":", "-.")[i % 4] for i, t in enumerate(targets)}  # tightest solid
    fig, axes = plt.subplots(2, len(scenes), figsize=(4.6 * len(scenes) + 2.6, 7.4), squeeze=False)
    for j, sc in enumerate(scenes):
        for i, (key, ylabel) in enumerate((("terms", "terms needed (each method's own count)"),
                                           ("bytes_per_vertex", "run-time memory per vertex (bytes)"))):
            ax = axes[i, j]
            for m in methods_:
                c = method_color(m)
                for t in targets:
                    rr = [r for r in rows if r["scene"] == sc and r["method"] == m and r["target"] == t]
                    # reached points joined; a not-reached exponent breaks the line (NaN)
                    ax.plot([r["exponent"] for r in rr], [r[key] if r["reached"] else float("nan") for r in rr],
                            style[t], color=c, marker="o", ms=4, lw=1.4)
                    no = [r for r in rr if not r["reached"]]
                    ax.plot([r["exponent"] for r in no], [r[key] for r in no], linestyle="none", marker="o", ms=7,
                            markerfacecolor="none", markeredgecolor=c, mew=1.3)
                first = min((r for r in rows if r["scene"] == sc and r["method"] == m and not r["reached"]),
                            key=lambda r: (r["exponent"], r["target"]), default=None)
                if first is not None:  # one direct label per method, at its first failure
                    ax.annotate("not reached", (first["exponent"], first[key]), textcoords="offset points",
                                xytext=(5, 6), ha="left", fontsize=6.5, color=c)
            ax.set_xscale("log", base=2)
            ax.set_yscale("log")
            xs = sorted({r["exponent"] for r in rows})
            ax.set_xticks(xs, [f"{x:g}" for x in xs])
            ax.grid(True, which="both", alpha=0.25)
            ax.set_xlabel("Phong exponent s (dimensionless)")
            ax.set_ylabel(ylabel)
            if i == 0:
                v = next(r["vertices"] for r in rows if r["scene"] == sc)
                ax.set_title(f"{sc} (test size, {v} vertices)", fontsize=10)
    handles = [Line2D([], [], color=method_color(m), lw=2, label=m) for m in methods_]
    handles += [Line2D([], [], color="k", ls=style[t], label=f"rel. RMSE <= {t:.0%}")
                for t in targets]
    handles.append(Line2D([], [], color="k", ls="none", marker="o", markerfacecolor="none",
                          label="not reached (at the\nlargest rung tried)"))
    fig.legend(handles=handles, loc="center right", fontsize=8, frameon=False)
    tgt = " / ".join(f"{t:.0%}" for t in targets)
    over = ("over the glossy region's pixels" if measure == "region" else "over the image")
    fig.suptitle(f"Smallest configuration whose image reaches relative RMSE {tgt} {over}\n"
                 f"(RMSE / mean radiance vs Mitsuba, direct lighting, {ref_spp} spp)", fontsize=11)
    fig.tight_layout(rect=(0, 0, 1 - 1.9 / (4.6 * len(scenes) + 2.6), 1))
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def restrict(cfg: YardstickConfig, *, scenes: Sequence[str] | None = None, exponents: Sequence[float] | None = None,
             methods: Sequence[str] | None = None, measure: str | None = None) -> YardstickConfig:
    """``cfg`` with only the named scenes (of ``cfg.scenes``), the given exponents and ladders, and the given
    ``measure`` (None: unchanged) — the CLI's ``--scenes/--exponents/--methods/--measure``."""
    if measure is not None:
        cfg = dataclasses.replace(cfg, measure=measure)   # (validated by the config)
    if scenes is not None:
        known = dict(cfg.scenes)
        bad = [n for n in scenes if n not in known]
        if bad or not scenes:
            raise ValueError(f"unknown scene(s) {bad or scenes!r} for this study; known: {sorted(known)}")
        cfg = dataclasses.replace(cfg, scenes=tuple((n, known[n]) for n in scenes))
    if exponents is not None:
        cfg = dataclasses.replace(cfg, exponents=tuple(float(x) for x in exponents))
    if methods is not None:
        bad = [n for n in methods if n not in TERM_LADDERS]
        if bad or not methods:
            raise ValueError(f"no term ladder registered for {bad or methods!r}; registered: {sorted(TERM_LADDERS)}")
        cfg = dataclasses.replace(cfg, methods=tuple(methods))
    return cfg


def terms_vs_exponent(out_dir: Path, *, quick: bool = False, config: YardstickConfig | None = None,
                      jobs: int = 1, scenes: Sequence[str] | None = None, exponents: Sequence[float] | None = None,
                      methods: Sequence[str] | None = None, worker_threads: int | None = None,
                      shared: bool = True, measure: str | None = None) -> list[Path]:
    """The one-yardstick study (module docstring) → terms_vs_exponent.csv/.png,
    ladder_evaluations.csv, summary.json. jobs: worker processes (`yardstick_table`); scenes,
    exponents, methods: a reduced run, measure: the searched error's pixels (`restrict`)."""
    cfg = restrict(config or (YARDSTICK_QUICK if quick else YARDSTICK), scenes=scenes, exponents=exponents,
                   methods=methods, measure=measure)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    n_methods = len(TERM_LADDERS) if cfg.methods is None else len(cfg.methods)
    bar = mahajan.progress_bar(len(cfg.scenes) * len(cfg.exponents) * n_methods, "terms-vs-exponent")
    t0, c0, ch0 = time.perf_counter(), time.process_time(), _children_cpu()
    rows, evals, floors = yardstick_table(cfg, progress=bar, jobs=jobs, worker_threads=worker_threads,
                                          shared=shared)
    bar.close()
    files = [mahajan.write_csv(out / "terms_vs_exponent.csv", rows),
             mahajan.write_csv(out / "ladder_evaluations.csv", evals),
             plot_yardstick(rows, out / "terms_vs_exponent.png", ref_spp=cfg.ref_spp, measure=cfg.measure)]
    secs: dict[str, dict] = {}
    for e in evals:
        d = secs.setdefault(e["method"], {"renders": 0, "seconds": 0.0, "cpu_seconds": 0.0})
        d["renders"] += 1
        d["seconds"] += e["seconds"]
        d["cpu_seconds"] += e["cpu_seconds"]
    summary = {"config": asdict(cfg), "noise_floor": floors, "per_method": secs,
               "total_seconds": time.perf_counter() - t0,
               "total_cpu_seconds": time.process_time() - c0 + _children_cpu() - ch0, "jobs": jobs,
               "not_monotone": [{k: r[k] for k in ("scene", "method", "target", "exponent", "terms", "note")}
                                for r in rows if not r["monotone"]]}
    path = out / "summary.json"
    path.write_text(json.dumps(summary, indent=2, default=float))
    return files + [path]


def _children_cpu() -> float:
    """CPU seconds of this process's finished child processes (the workers of ``jobs`` > 1)."""
    import os

    t = os.times()
    return t.children_user + t.children_system


def _terms_vs_exponent_study(out_dir: Path, *, quick: bool = False, jobs: int | None = None,
                             scenes: Sequence[str] | None = None, exponents: Sequence[float] | None = None,
                             methods: Sequence[str] | None = None, measure: str | None = None) -> list[Path]:
    """``run_bench.py study terms-vs-exponent``: `terms_vs_exponent` with ``default_jobs()``
    worker processes unless told (the Python function's default stays in-process: ladders
    registered at run time, e.g. by tests, exist only there)."""
    return terms_vs_exponent(out_dir, quick=quick, jobs=default_jobs() if jobs is None else jobs,
                             scenes=scenes, exponents=exponents, methods=methods, measure=measure)


# -- terms-own-criteria: each contributor under its own criterion ------------------------------

OWN_CRITERIA_EXPONENTS = (1, 2, 4, 8, 16, 32, 64, 128, 256)
OWN_CRITERIA_EXPONENTS_QUICK = (2,)


def terms_own_criteria(out_dir: Path, *, quick: bool = False) -> list[Path]:
    """Every registered terms contributor at every exponent → terms_by_method.csv/.png (each curve
    its own criterion, stated in the legend) and, if registered, error_vs_terms.csv."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    plt = pyplot()
    exps = OWN_CRITERIA_EXPONENTS_QUICK if quick else OWN_CRITERIA_EXPONENTS
    s_err = mahajan.FIG6_S_QUICK if quick else mahajan.FIG6_S
    bar = mahajan.progress_bar(len(TERMS_CONTRIBUTORS) * len(exps) + len(ERROR_VS_TERMS) * len(s_err),
                               "terms-own-criteria")
    recs = terms_table(list(exps), progress=bar)
    files = [mahajan.write_csv(out / "terms_by_method.csv", [asdict(r) for r in recs])]
    fig, ax = plt.subplots(figsize=(10, 4.5))
    for name in sorted({r.method for r in recs}):
        rr = [r for r in recs if r.method == name]
        ax.plot([r.exponent for r in rr], [r.terms for r in rr], "o--" if name.endswith("_separated") else "o-",
                color=method_color(name), label=f"{name}: {rr[0].target_kind} {rr[0].target:g}")
    ax.set_xscale("log", base=2)
    ax.set_yscale("log")
    ax.set_xlabel("Phong exponent s (dimensionless)")
    ax.set_ylabel("terms needed (each method's own count)")
    ax.set_title("Terms vs exponent, each method under its OWN criterion (not comparable;\n"
                 "see terms-vs-exponent for one yardstick)", fontsize=10)
    ax.grid(True, which="both", alpha=0.25)
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0), frameon=False)
    files.append(save_fig(fig, out / "terms_by_method.png", plt))
    if ERROR_VS_TERMS:
        files += mahajan.error_vs_terms_table(out, dict(ERROR_VS_TERMS), s_err, progress=bar, plot=False)
    bar.close()
    return files


register_study(Study("terms-vs-exponent",
                     "One yardstick: smallest configuration of every method whose image reaches 5 % / 10 % "
                     "relative RMSE vs Mitsuba, terms and bytes per vertex vs Phong exponent 1-256",
                     _terms_vs_exponent_study))
register_study(Study("terms-own-criteria",
                     "Terms vs Phong exponent of every method under its own criterion (energy, tensor "
                     "error, shading error) + Mahajan Fig. 6 rendered error vs K", terms_own_criteria))
