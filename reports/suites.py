"""Benchmark suites and the capability matrix that turns a suite into cells.

* ``smoke``: test-size scene(s), sequences V and VBL of 3 frames, 64-spp references, bounces 0,
  every available method, each cell in its own spawned process (peak RSS per cell). A few minutes
  on 2 cores.
* ``nightly``: five library scenes at bench size (below), all methods, V / VB / VBL / L / E / VL
  (+ P for articulated scenes), bounces 0 (+ 1, 2 on V and L for methods with ``max_bounces > 0``),
  4-frame sequences with 2 scored frames, 256-spp references, the oracle at 4+4 samples. Target ≤ 30
  min on 2 cores with a warm reference cache (the README and the report header give the measured
  wall time; how the suite was cut to fit is beside its definition).

* ``perf``: chess and creature at bench size, every frame kind (V, VB, VBL, L, E, VL, P), 4 timed
  frames: the suite the frame-time and roofline numbers come from. Triple product runs twice, shaded
  per pixel (its default) and per vertex (Ma 2006 §3.3).

``Capabilities.why_not`` decides which cells are in scope; out-of-scope cells are still planned,
with their reason in ``Cell.na``, so the report shows the whole matrix.
"""
from __future__ import annotations

import importlib
import json
from dataclasses import dataclass
from pathlib import Path

from reports.cells import FULL, SCENE_FILE_PREFIX, Cell, canonical_config, capability_bounces


@dataclass(frozen=True)
class Suite:
    """What a suite runs (see the module docstring).

    scenes: library names (None = every scene of the backend). kinds: sequence kinds of every
    scene; dynamic_kinds: added for scenes with a skeleton. extra_bounces: bounce counts tried
    besides 0 for methods with ``max_bounces > 0``, on the kinds in bounce_kinds (None = every
    kind; the other kinds' extra-bounce cells are not planned: a budget choice, not a capability,
    so they are not n/a rows either). configs: (method, config JSON) pairs; a method
    without any runs its default config. methods: None = every available method.
    """

    name: str
    size: str
    kinds: tuple[str, ...]
    n_frames: int
    ref_spp: int
    scenes: tuple[str, ...] | None = None
    dynamic_kinds: tuple[str, ...] = ("P",)
    score_frames: tuple[int, ...] = ()
    spp_side: int = 2  # = references.render's default coverage S
    extra_bounces: tuple[int, ...] = ()
    bounce_kinds: tuple[str, ...] | None = None
    methods: tuple[str, ...] | None = None
    configs: tuple[tuple[str, str], ...] = ()
    eq_err_spp: tuple[int, ...] = ()
    fresh_calibration: bool = False  # `Cell.fresh_calibration`: Mitsuba's equal-error renders timed in the run
    isolate: bool | str = True
    threads: int | None = None
    seed: int = 0


# ZH (Nowrouzezahrai 2008) beside its published setting: SH order 8 and the Phong lobe with the
# cos θi the paper's convolution leaves out (§4.2) — the physically defined Phong that the Mitsuba
# reference renders. Under the suites' sun probes the paper's order-4 setting is `suspect` on
# lighting changes (a region 1.5-2.5x too bright: the sun rings through the order-4 Phong lobe and
# the missing cos θi lets a grazing sun in); this one is ok except where a sun sits just below a
# horizon that only the 2-lobe ZH visibility fit blurs (bunny L; methods/zh_shadow/method.py).
ZH_PHYSICAL = '{"order":8,"specular":"cosine"}'
# The same shaded per vertex (the paper's GPU shading, §4.3) for the bench-size nightly: the cosine
# variant has no fast path, and per sample it takes ~9 s per 256² frame against ~1 s per vertex, for
# the same error (sphere_plane bench V: relative RMSE 0.262 per sample, 0.263 per vertex).
ZH_PHYSICAL_VERTEX = '{"order":8,"shading":"vertex","specular":"cosine"}'

# Triple product shaded per vertex (Ma 2006 §3.3: "evaluate Equation 7 for each vertex and then
# interpolate vertices' colors to rasterize visible triangles", the mode most all-frequency
# relighting used; the paper's per-pixel shading is its default). Per frame it shades ~10⁴ vertices
# instead of 256² × 4 samples.
TP_VERTEX = '{"shading":"vertex"}'

# smoke: one synthetic scene and one real scan under a captured probe (bunny: Stanford bunny, the
# "sunrise" probe); view (V), view+BRDF+lighting (VBL) and the two lighting-only kinds (L: rotation
# about a tilted axis, E: captured probes swapped) so every method is scored on relighting.
SMOKE = Suite(name="smoke", size="test", scenes=("sphere_plane", "bunny"), kinds=("V", "VBL", "L", "E"),
              dynamic_kinds=("P",), n_frames=3, ref_spp=64, eq_err_spp=(16, 64), isolate=True,
              # PTT twice: its default (the scene's own lobes) and the paper's PCA BRDF basis; ZH twice:
              # the paper's (order 4, Phong about R without cos θi) and ZH_PHYSICAL (below)
              configs=(("ptt", "{}"), ("ptt", '{"basis":"pca"}'), ("zh_shadow", "{}"), ("zh_shadow", ZH_PHYSICAL)))
# nightly: five of the eight library scenes at bench size — two synthetic static ones (sphere_plane,
# chess: three BRDF families), the alcove (interreflection), the articulated creature, and a real scan
# under a captured probe (bunny) — every frame kind (the relighting kinds L, E, VL included) with 4
# frames, 2 of them scored. The other three scenes (shadow_detail, dragon, character) are in the test
# suite at test size.
# Budget (≤ 30 min on 2 cores with a warm reference cache), measured on the first end-to-end run
# (2026-12-02, 259 in-scope cells, cold caches, a machine shared with two other jobs): 3 of 5 scenes
# took 49 min — ~11 s per in-scope cell, and ~45 s per cell of ZH's cosine variant shaded per sample
# (it has no fast path: 9 s per 256² frame). Cut, without dropping a scene, a frame kind or a method:
# (1) the extra bounce counts of PTT and SH PRT run on V (Sun 2007 Fig. 11) and L (relighting with
# interreflection) only, not on VB / VBL / E / VL (bounce_kinds; −56 cells, ~25 % of the time);
# (2) ZH's cosine variant is shaded per vertex (ZH_PHYSICAL_VERTEX: the paper's GPU shading, same
# error on sphere_plane bench, 1 s per frame). Cells run in-process (spawning one child per cell costs
# ~6 s of imports each); ``--isolate`` gives per-cell peak RSS at that price. On more machines:
# ``--executor dask --scheduler tcp://host:8786`` (reports/executors.py, README). Precomputations are
# cached across nights while the code each method runs is unchanged (reports/precompute_cache.py).
NIGHTLY = Suite(name="nightly", size="bench", scenes=("sphere_plane", "chess", "alcove", "creature", "bunny"),
                kinds=("V", "VB", "VBL", "L", "E", "VL"), dynamic_kinds=("P",),
                n_frames=4, score_frames=(1, 3), ref_spp=256, extra_bounces=(1, 2, FULL),
                bounce_kinds=("V", "L"),
                configs=(("oracle", '{"brdf_samples":4,"light_samples":4}'),
                         # one-bounce lighting 6×4×4 instead of 6×8×8: T¹ 0.75 GiB instead of 3 GiB on
                         # chess (bench); measured on the Fig. 8 sweep (methods.ptt.study fig8)
                         ("ptt", '{"light_res_1":4}'), ("zh_shadow", "{}"), ("zh_shadow", ZH_PHYSICAL_VERTEX)),
                eq_err_spp=(32, 128, 256), isolate=False)
# perf: what the run-time numbers (frame times, roofline efficiency, equal-error speedup) come from —
# every method on two bench-size scenes (chess: static, three BRDF families; creature: articulated),
# every frame kind a method claims, 1 warm-up + 4 timed frames, one scored frame per sequence (the
# equal-error speedup needs its error), precomputations shared through the precompute cache. Each
# method configuration's cells run in a spawned process of their own (isolate="method",
# reports.executors.MethodProcessExecutor): in one process a cell's frame times depended on the
# other methods' cells run before it (session 32: ZH order-8 L 2.5-2.8 ms in two full runs, 1.2-1.4
# alone); ~6 s of imports per configuration.
PERF = Suite(name="perf", size="bench", scenes=("chess", "creature"), kinds=("V", "VB", "VBL", "L", "E", "VL"),
             dynamic_kinds=("P",), n_frames=5, score_frames=(4,), ref_spp=128, eq_err_spp=(32, 128),
             fresh_calibration=True, isolate="method", configs=(("oracle", '{"brdf_samples":4,"light_samples":4}'), ("ptt", '{"light_res_1":4}'),
                                     # in-out twice: eq. 4 per G-buffer sample (default) and per vertex,
                                     # Gouraud-interpolated (the paper's run time, Mahajan 2008 §6)
                                     ("inout", "{}"), ("inout", '{"shading":"vertex"}'),
                                     # ZH twice, as the nightly: the paper's setting and the physical one per vertex
                                     ("zh_shadow", "{}"), ("zh_shadow", ZH_PHYSICAL_VERTEX),
                                     # triple product both ways Ma 2006 §3.3 describes: per pixel
                                     # (its default) and per vertex (eq. 7 at the vertices, colours
                                     # interpolated: the "per-vertex shading" pseudocode of §3.3)
                                     ("triple_product", "{}"), ("triple_product", TP_VERTEX)))
SUITES = {"smoke": SMOKE, "nightly": NIGHTLY, "perf": PERF}


def get_suite(name: str) -> Suite:
    try:
        return SUITES[name]
    except KeyError:
        raise ValueError(f"unknown suite {name!r}; available: {', '.join(SUITES)}") from None


def _configs_for(suite: Suite, method: str) -> list[str]:
    cfgs = [canonical_config(c) for m, c in suite.configs if m == method]
    return cfgs or ["{}"]


def plan_cells(suite: Suite, *, methods: list[str] | None = None, scenes: list[str] | None = None,
               backend: str = "reports.backend", plugins: tuple[str, ...] = (),
               isolate: bool | str | None = None, device: str = "cpu") -> list[Cell]:
    """Every cell of ``suite`` (in-scope and n/a), optionally restricted to ``methods``/``scenes``.

    ``scenes`` may contain ``"file:<path>"`` entries (TOML scene files).
    """
    from methods.registry import available_methods, get_method
    from reports.backend import load_backend

    be = load_backend(backend)
    for mod in plugins:
        importlib.import_module(mod)
    scene_names = list(scenes or suite.scenes or be.scene_names())
    method_names = list(methods or suite.methods or available_methods())
    classes = {}
    for m in method_names:
        try:
            classes[m] = get_method(m)
        except KeyError as e:
            raise ValueError(str(e.args[0])) from None
    library = set(be.scene_names()) if hasattr(be, "scene_names") else set()
    cells: list[Cell] = []
    sources: dict[str, str] = {}  # scene name → where it came from (library or file)
    for sc in scene_names:
        scene = _load_scene(be, sc, suite.size)
        if sc.startswith(SCENE_FILE_PREFIX):  # a TOML scene file: shown by its name, loaded by its path
            scene_file = sc[len(SCENE_FILE_PREFIX):]
            name = str(getattr(scene, "name", "") or "") or Path(scene_file).stem
            src = scene_file
            if name in library:
                raise ValueError(f"{Path(scene_file).name}: scene name {name!r} is a library scene's name; "
                                 f"give the file another 'name'")
        else:
            name, scene_file, src = sc, "", "the library"
        if name in sources:
            raise ValueError(f"scene name {name!r} is used twice ({sources[name]} and {src}); scene names must be unique")
        sources[name] = src
        scene_hash = scene.content_hash() if hasattr(scene, "content_hash") else ""
        dynamic = be.is_dynamic(scene) if hasattr(be, "is_dynamic") else False
        kinds = tuple(suite.kinds) + (tuple(suite.dynamic_kinds) if dynamic else ())
        for m, cls in classes.items():
            for cfg in _configs_for(suite, m):
                caps = cls(**json.loads(cfg)).capabilities  # per instance: claims may depend on the config
                bounces = (0,) + (tuple(suite.extra_bounces) if caps.max_bounces > 0 else ())
                for k in kinds:
                    for b in bounces:
                        if b != 0 and suite.bounce_kinds is not None and k not in suite.bounce_kinds:
                            continue
                        na = caps.why_not(scene, k, capability_bounces(b))
                        cells.append(Cell(scene=name, scene_file=scene_file, scene_hash=scene_hash, size=suite.size,
                                          kind=k, method=m, config=cfg, bounces=b,
                                          n_frames=suite.n_frames, seed=suite.seed, score_frames=suite.score_frames,
                                          ref_spp=suite.ref_spp, spp_side=suite.spp_side, eq_err_spp=suite.eq_err_spp,
                                          fresh_calibration=suite.fresh_calibration,
                                          threads=suite.threads, isolate=suite.isolate if isolate is None else isolate,
                                          na=na, backend=backend, plugins=tuple(plugins), device=device,
                                          score_full_gi=caps.max_bounces > 0 and b != FULL))
    return cells


def _load_scene(be, name: str, size: str):
    """``be.get_scene`` with an unknown name as one ``ValueError`` line (like an unknown method)."""
    try:
        return be.get_scene(name, size)
    except KeyError as e:
        raise ValueError(str(e.args[0]) if e.args else f"unknown scene {name!r}") from None


def reference_jobs(cells: list[Cell]) -> list[tuple[str, str, str, int, int, int, int, tuple[int, ...], tuple[int, ...]]]:
    """Distinct reference renders the in-scope cells need: (scene, size, kind, n_frames, seed,
    bounces, spp, frames, eq_err_spp); scene is what the backend loads (``Cell.scene_ref``)."""
    seen = []
    for c in cells:
        if c.na is not None:
            continue
        j = (c.scene_ref, c.size, c.kind, c.n_frames, c.seed, c.bounces, c.ref_spp, tuple(c.scored()), tuple(c.eq_err_spp))
        if j not in seen:
            seen.append(j)
        if c.score_full_gi and c.bounces != FULL:  # the full-GI reference it is also scored against
            jf = (c.scene_ref, c.size, c.kind, c.n_frames, c.seed, FULL, c.ref_spp, tuple(c.scored()), ())
            if jf not in seen:
                seen.append(jf)
    return seen
