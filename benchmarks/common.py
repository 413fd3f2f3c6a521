"""The set-up every benchmark script starts from: scene → frames → G-buffers → references.

    scene, frames, gbuffers, references = setup("alcove", "test", ref_spp=256, bounces=(0, 1))

A thin wrapper of `references.setup.frame_setup` (the same helper the paper studies in
``methods/<m>/study.py`` use) that also builds the scene by name.
"""
from __future__ import annotations

import contextlib

from typing import Sequence

from references.setup import frame_setup
from scenes.library import get_scene


def setup(scene_name, size: str = "test", *, kind: str = "V", n_frames: int = 1, seed: int = 0,
          spp_side: int = 2, ref_spp: int = 0, bounces: Sequence[int | None] = (0,), frames=None):
    """(scene, frames, gbuffers, references) for ``scene_name`` (a library name, or a `Scene`).

    frames: ``make_sequence(scene, kind, n_frames, seed)`` unless given; gbuffers: one per frame
    (``spp_side``² samples per pixel); references: bounces → `references.render.Reference` of the
    first frame at ``ref_spp`` samples per pixel (seed ``seed``; empty when ``ref_spp`` is 0).
    """
    scene = get_scene(scene_name, size) if isinstance(scene_name, str) else scene_name
    st = frame_setup(scene, frames=frames, kind=kind, n_frames=n_frames, seed=seed, spp_side=spp_side,
                     ref_spp=ref_spp, bounces=bounces)
    return st.scene, st.frames, st.gbuffers, st.references


SETTLE_SECONDS = float(__import__("os").environ.get("PRTBENCH_SETTLE", "0.2"))


def settle() -> None:
    """Idle ``PRTBENCH_SETTLE`` seconds (default 0.2) before a timed frame of a same-process A/B.

    The perf suite times each frame right after the harness made its G-buffer (Mitsuba) and after
    idle time, not right after the previous frame: measured here (2026-12-05, ZH paper L, creature
    bench, quiet machine) a frame after 0.2 s idle took 4.3 ms at 1 thread against 2.6 ms back to
    back (3.5 ms after 20 ms idle, 2.9 after 5 ms) and 3.5 against 1.8 ms at 2 threads, and a frame
    right after `make_gbuffer` 3.8 / 3.1 ms. Caches, TLBs and the OpenMP pool cool while the vCPU
    idles, so a back-to-back A/B favours changes that keep more state warm (session 19's kept ZH
    plane operator: 1.15x back to back, slower in the suite). Settling makes an A/B measure the
    condition the suite measures. 0 restores back-to-back frames."""
    if SETTLE_SECONDS > 0:
        import time

        time.sleep(SETTLE_SECONDS)


def median_time(fn, repeats: int = 5) -> float:
    """Median wall seconds of ``repeats`` calls of ``fn`` after one warm-up call."""
    import statistics
    import time

    fn()
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts)


def wall_cpu_time(fn, repeats: int = 5) -> dict[str, float]:
    """Median wall and process-CPU seconds (``"wall"``, ``"cpu"``) of ``repeats`` calls of ``fn``
    after one warm-up call (process CPU time is the less load-sensitive of the two)."""
    import statistics
    import time

    fn()
    ts, cs = [], []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        ts.append(time.perf_counter() - t0)
        cs.append(time.process_time() - c0)
    return {"wall": statistics.median(ts), "cpu": statistics.median(cs)}


def frame_args(ap, *, scene: str, config: str = "{}", frames: int = 5, kinds: Sequence[str] = ("V", "L", "E")):
    """The options every frame-timing benchmark takes (scene, size, method config, frames per kind,
    torch threads, G-buffer samples per pixel side, sequence kinds), added to ``ap``."""
    ap.add_argument("--scene", default=scene)
    ap.add_argument("--size", default="bench")
    ap.add_argument("--config", default=config)
    ap.add_argument("--frames", type=int, default=frames)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--spp-side", type=int, default=2)
    ap.add_argument("--kinds", nargs="+", default=list(kinds))
    return ap


def precomputed(cls, scene, config: dict):
    """``(cls(**config) precomputed on scene, precompute seconds or None when it came from the
    cache)`` through the harness's one precompute cache (`reports.precompute_cache`: tensors only,
    hash-checked, nothing in the cache folder can run code; issue 17)."""
    from reports import precompute_cache
    from reports.cells import canonical_config

    m = cls(**config)
    pre = precompute_cache.precompute(m, scene, canonical_config(config))
    return m, (None if pre["cached"] else pre["seconds"])


def inout_loop_state(scene_name: str, size: str, n_frames: int):
    """The per-sample C loop's inputs (``methods.inout.native_sample.shade``) for the loop benchmarks: the
    scene, ``n_frames`` V frames (seed 1, 2×2 samples) and their G-buffers, in-out precomputed (the cache)
    with its fast path's caches reset, frame 0 rendered (its c complete), the static arrays and each
    region's c — ``(scene, frames, gbs, m, st, cs)``."""
    from methods.inout import InOut

    scene, frames, gbs, _ = setup(scene_name, size, kind="V", n_frames=n_frames, seed=1, spp_side=2)
    m, _ = precomputed(InOut, scene, {})
    m._fast = None
    m._reset_cache()
    m.render(frames[0], gbs[0])
    return scene, frames, gbs, m, m._fast_static(), [m._cf[r.name] for r in m.regions]


def inout_regions(m) -> dict:
    """K and vertex count per region of a precomputed `methods.inout.InOut` (the benchmarks' header)."""
    return {"K": {r.name: r.K for r in m.regions}, "vertices": {r.name: int(r.verts.numel()) for r in m.regions}}


def machine_limits(out: dict, bw: list, peak: list) -> tuple[float, float]:
    """Measure triad bandwidth and matmul peak once more (after the frames; ``bw``/``peak`` hold the
    measurements from before them), record both lists in ``out`` and return the best of each."""
    from reports import measure

    bw.append(measure.triad_bandwidth())
    peak.append(measure.matmul_peak())
    out.update(triad_bandwidth=bw, matmul_peak=peak)
    return max(bw), max(peak)


def roofline_columns(kinds: dict, labels: Sequence[str], B: float, Pk: float) -> None:
    """Per kind's result r and label w: r[w_efficiency], r[w_bound] from r[w_bytes], r[w_flops] and
    r[w_median_s] (`reports.measure.roofline`)."""
    from reports import measure

    for r in kinds.values():
        for w in labels:
            r[f"{w}_efficiency"], r[f"{w}_bound"] = measure.roofline(r[f"{w}_bytes"], r[f"{w}_flops"], B, Pk,
                                                                     r[f"{w}_median_s"])


# root → the ``methods.*`` modules of the checkout at root imported so far (`checkout_class`,
# `checkout_modules`)
_CHECKOUT_MODULES: dict[str, dict] = {}


def _methods_modules() -> dict:
    import sys

    return {k: v for k, v in sys.modules.items() if k == "methods" or k.startswith("methods.")}


@contextlib.contextmanager
def checkout_modules(root: str):
    """Within the block, ``import methods...`` gives the modules of the checkout at ``root`` (those
    `checkout_class` imported, and any imported in such a block, from ``root``'s files); this
    checkout's are restored after it. Run a base class's frames inside it: a module that imports
    another lazily, inside a function, at call time, otherwise finds THIS checkout's module in
    ``sys.modules`` (found in session 28: `benchmarks.ptt_ab`'s base frames ran this checkout's
    ``methods/ptt/native.py``, so a change of it read as ~1.00x). Swapping costs ~0.1 ms; keep it
    outside the timed region."""
    import sys

    mine = _methods_modules()
    for k in mine:
        del sys.modules[k]
    sys.modules.update(_CHECKOUT_MODULES.setdefault(root, {}))
    sys.path.insert(0, root)
    try:
        yield
    finally:
        sys.path.remove(root)
        theirs = _methods_modules()
        _CHECKOUT_MODULES[root] = theirs
        for k in theirs:
            del sys.modules[k]
        sys.modules.update(mine)


def checkout_class(root: str, module: str, name: str):
    """Class ``name`` of module ``module`` (e.g. ``"methods.ptt.method"``, ``"PTT"``) as the checkout at
    ``root`` has it, imported beside this checkout's (its ``methods`` package under the same names,
    then this checkout's modules restored): the 'before' of a same-process A/B. Its module-level
    imports are the checkout's; render its frames inside `checkout_modules` so that its lazy
    (call-time) imports are too."""
    import importlib

    mine = getattr(importlib.import_module(module), name)
    with checkout_modules(root):
        importlib.import_module(module)  # the checkout's modules
        mods = _methods_modules()
    cls = getattr(mods[module], name)
    if cls is mine or not mods[module].__file__.startswith(root):
        raise RuntimeError(f"could not import the base {name} from {root}")
    return cls


def checkout_fingerprint(root: str, module: str) -> str:
    """``reports.store.code_closure_fingerprint`` of ``module`` in the checkout at ``root`` (the key of its
    precomputations in the harness's cache)."""
    import subprocess
    import sys

    cmd = f"from reports.store import code_closure_fingerprint as f; print(f({module!r}))"
    out = subprocess.run([sys.executable, "-c", cmd], cwd=root, capture_output=True, text=True, check=True)
    return out.stdout.strip().splitlines()[-1]


def ab_report(out: dict, kinds: dict, B: float, Pk: float, title: str, *, show_mb: bool = False) -> None:
    """The end of a same-process A/B run (``benchmarks.vview``, ``benchmarks.sh_prt``): each kind's
    roofline efficiency of the new code (``max(bytes / B, flops / Pk)`` over its wall and CPU time),
    then the whole result as JSON and a table — base and new CPU / wall ms, their ratios, the
    efficiencies, the largest relative image difference — and any ``out["micro"]`` lines.
    ``kinds``: kind → {"base"/"new": {"wall_ms", "cpu_ms"}, bytes, flops, cpu_ratio, wall_ratio,
    rel_err}; ``out`` gets ``kinds`` and ``load_end``."""
    import json
    import os

    for r in kinds.values():
        tmin = max(r["bytes"] / B, r["flops"] / Pk)
        r["eff_new_wall"] = tmin / (r["new"]["wall_ms"] / 1e3)
        r["eff_new_cpu"] = tmin / (r["new"]["cpu_ms"] / 1e3)
    out["kinds"] = kinds
    out["load_end"] = os.getloadavg()
    print(json.dumps(out, indent=1, default=float))
    print(f"\n{title}, load {out['load'][0]:.1f}→{out['load_end'][0]:.1f}, triad {B / 1e9:.1f} GB/s, "
          f"sgemm {Pk / 1e9:.1f} GFLOP/s")
    mb = f" {'MB':>6}" if show_mb else ""
    print(f"{'kind':4} {'base cpu':>9} {'new cpu':>8} {'ratio':>6} {'base wall':>9} {'new wall':>8} {'ratio':>6}{mb} "
          f"{'eff(wall)':>9} {'eff(cpu)':>9} {'rel err':>8}")
    for kind, r in kinds.items():
        mb = f" {r['bytes'] / 1e6:6.1f}" if show_mb else ""
        print(f"{kind:4} {r['base']['cpu_ms']:9.2f} {r['new']['cpu_ms']:8.2f} {r['cpu_ratio']:6.2f} "
              f"{r['base']['wall_ms']:9.2f} {r['new']['wall_ms']:8.2f} {r['wall_ratio']:6.2f}{mb} "
              f"{100 * r['eff_new_wall']:8.1f}% {100 * r['eff_new_cpu']:8.1f}% {r['rel_err']:8.1e}")
    for k, v in out.get("micro", {}).items():
        print(f"micro {k:22}: " + ", ".join(f"{x} {y:.3g}" for x, y in v.items()))


def ab_frames(new, base, reference, frames, gbs, kind: str, *, base_root: str | None = None) -> dict:
    """Same-process A/B of one sequence: ``new`` and ``base`` (two method objects sharing one
    precomputation) render every frame, alternating which goes first (the same machine load for
    both); frames 0 and 1 warm up. ``reference(frame, gbuffer)`` is the slow path each new image is
    checked against. ``base_root``: the checkout ``base``'s class came from (`checkout_class`); its
    frames render inside `checkout_modules` (entered before the clock starts), so its lazy imports are
    that checkout's too. → {"base"/"new": median {"wall_ms", "cpu_ms"}, bytes, flops (the new object's
    ``frame_cost(kind, …)``), rel_err (largest |new − reference| / max |reference|), cpu_ratio,
    wall_ratio} — a row of `ab_report`."""
    import statistics
    import time

    t = {"new": ([], []), "base": ([], [])}
    err = 0.0
    for i, (f, g) in enumerate(zip(frames, gbs)):
        for which in (("new", "base") if i % 2 == 0 else ("base", "new")):
            mm = new if which == "new" else base
            with checkout_modules(base_root) if which == "base" and base_root else contextlib.nullcontext():
                settle()
                t0, c0 = time.perf_counter(), time.process_time()
                img = mm.render(f, g)
                w, c = time.perf_counter() - t0, time.process_time() - c0
            if i >= 2:
                t[which][0].append(w)
                t[which][1].append(c)
            if which == "new":
                rimg = reference(f, g)
                err = max(err, float((img - rimg).abs().max() / rimg.abs().max().clamp_min(1e-12)))
    r = {k: {"wall_ms": 1e3 * statistics.median(v[0]), "cpu_ms": 1e3 * statistics.median(v[1])} for k, v in t.items()}
    cost = new.frame_cost(kind, gbs[-1].num_samples, pixels=gbs[-1].height * gbs[-1].width)
    r.update(bytes=cost.bytes, flops=cost.flops, rel_err=err,
             cpu_ratio=r["base"]["cpu_ms"] / r["new"]["cpu_ms"], wall_ratio=r["base"]["wall_ms"] / r["new"]["wall_ms"])
    return r


def ab_options(ap, *, config: str = "{}", kinds: Sequence[str] = ("V",)) -> None:
    """The options every same-process A/B against another checkout takes (`benchmarks.vview`,
    `benchmarks.zh_pose_ab`): scene, size, config, frames, threads, kinds, --baseline (the checkout
    whose method is the "before") and --precompute-code (take the precomputation from the harness
    cache entry of the code in DIR: a branch that changes only run-time code has the same state)."""
    ap.add_argument("--scene", default="creature")
    ap.add_argument("--size", default="bench")
    ap.add_argument("--config", default=config)
    ap.add_argument("--frames", type=int, default=9)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--kinds", nargs="+", default=list(kinds))
    ap.add_argument("--baseline", required=True)
    ap.add_argument("--precompute-code", default=None)


def apply_ab_options(a) -> None:
    """Thread count and --precompute-code of `ab_options`, applied to this process."""
    import torch

    torch.set_num_threads(a.threads)
    if a.precompute_code:
        from reports import precompute_cache
        from reports.store import code_closure_fingerprint

        precompute_cache._process_fingerprint = lambda mod: code_closure_fingerprint(mod, a.precompute_code)


def load_file_module(path: str, name: str):
    """The module at ``path`` imported as ``name`` (beside this checkout's modules of the same file:
    the "before" of a same-process A/B, e.g. another checkout's ``methods/<m>/runtime.py``)."""
    import importlib.util
    import sys

    spec = importlib.util.spec_from_file_location(name, path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    spec.loader.exec_module(mod)
    return mod


class registry_kept:
    """``with registry_kept(): ...`` — the method registry as it was before the block: loading another
    checkout's method module (`load_file_module`) registers its class under this tree's name."""

    def __enter__(self):
        from methods import base

        self._saved = dict(base._REGISTRY)
        return self

    def __exit__(self, *exc):
        from methods import base

        base._REGISTRY.clear()
        base._REGISTRY.update(self._saved)
        return False

