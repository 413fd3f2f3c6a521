"""The set-up every benchmark script starts from: scene → frames → G-buffers → references.

    scene, frames, gbuffers, references = setup("alcove", "test", ref_spp=256, bounces=(0, 1))

A thin wrapper of `references.setup.frame_setup` (the same helper the paper studies in
``methods/<m>/study.py`` use) that also builds the scene by name.
"""
from __future__ import annotations

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
