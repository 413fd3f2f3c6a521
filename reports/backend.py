"""The harness's view of the rest of the project: scenes, sequences, G-buffers, references, metrics.

A cell names its backend by module (``Cell.backend``, default ``"reports.backend"``) so it stays
picklable and a spawned child process can import the same backend; tests use
``testing.fakes`` (tiny torch-only scenes and references). A backend module provides:

``get_scene(name, size)``, ``make_sequence(scene, kind, n_frames, seed)``,
``make_gbuffer(scene, frame, S)``, ``render_reference(scene, frame, *, bounces, spp, seed)``,
``all_metrics(img, ref, mask, *, exposure)``, ``make_exposure(ref, mask)``, ``geometry(scene, frame) -> (V (N,3), F (M,3))``,
``reference_seconds(ref) -> float | None`` and ``render_reference_uncached(...)`` (for timing).
"""
from __future__ import annotations

import importlib
import time
from pathlib import Path

from reports.cells import SCENE_FILE_PREFIX


def load_backend(name: str = "reports.backend"):
    """Import a backend module by name (``ValueError`` if it lacks a required function)."""
    mod = importlib.import_module(name)
    need = ("get_scene", "make_sequence", "make_gbuffer", "render_reference", "all_metrics", "geometry")
    missing = [f for f in need if not hasattr(mod, f)]
    if missing:
        raise ValueError(f"backend {name!r} lacks {missing}")
    return mod


def _ensure_mitsuba() -> None:
    from references.mitsuba_setup import ensure_variant

    ensure_variant()


def get_scene(name: str, size: str = "test"):
    """A library scene by name, or a TOML scene file given as ``"file:<path>"``."""
    if name.startswith(SCENE_FILE_PREFIX):
        from scenes.scenefile import load_scene_file

        # the suite's size: meshes decimated to its vertex budget, film and env map at its size
        return load_scene_file(Path(name[len(SCENE_FILE_PREFIX):]), size=size)
    from scenes.library import get_scene as _get

    try:
        return _get(name, size)
    except KeyError as e:  # the library names the available scenes; one line like an unknown method
        raise ValueError(str(e.args[0]) if e.args else f"unknown scene {name!r}") from None


def scene_names() -> list[str]:
    from scenes.library import SCENES

    return list(SCENES)


def make_sequence(scene, kind: str, n_frames: int, seed: int):
    from scenes.sequences import make_sequence as _mk

    return _mk(scene, kind, n_frames, seed)


def make_gbuffer(scene, frame, S: int):
    _ensure_mitsuba()
    from references.gbuffer import make_gbuffer as _mk

    return _mk(scene, frame, S)


def _ref_bounces(bounces: int) -> int | None:
    """Cells say −1 for full GI; ``references.render`` says None."""
    return None if bounces is not None and bounces < 0 else bounces


def render_reference(scene, frame, *, bounces: int, spp: int, seed: int, spp_side: int = 2, use_cache: bool = True):
    _ensure_mitsuba()
    from references.render import render_reference as _r

    return _r(scene, frame, bounces=_ref_bounces(bounces), spp=spp, seed=seed, spp_side=spp_side, use_cache=use_cache)


def _dr_threads() -> int | None:
    try:
        import drjit as dr

        return int(dr.thread_count())
    except Exception:
        return None


def set_threads(n: int) -> None:
    """Dr.Jit's thread pool too, so references and methods are timed with the same threads."""
    import drjit as dr

    dr.set_thread_count(n)


def reference_seconds(ref) -> float | None:
    """Mitsuba's frame time of a reference, what the equal-error speedup charges it: its two renders
    without the scene's export and load or Dr.Jit's kernel compilation (``frame_seconds`` of
    `references.render.render_halves`; a method's frame time excludes its precomputation and
    compilation likewise). None for a reference recorded before that split (its ``render_seconds``
    include both: up to 0.75 s of compilation on a VB frame's new materials), so `timed_reference`
    times a new render."""
    meta = getattr(ref, "meta", None) or {}
    v = meta.get("frame_seconds") if isinstance(meta, dict) else None
    if isinstance(v, (int, float)) and v > 0:
        return float(v)
    return None


def timed_reference(scene, frame, *, bounces: int, spp: int, seed: int, spp_side: int = 2):
    """(reference, seconds): the render time recorded in the reference's meta (kept by the cache,
    so a cache hit still reports the original render time) if it was rendered with this process's
    Dr.Jit thread count; else the wall time of an uncached render here."""
    ref = render_reference(scene, frame, bounces=bounces, spp=spp, seed=seed, spp_side=spp_side)
    sec = reference_seconds(ref)
    if sec is not None and ref.meta.get("threads") in (None, -1, _dr_threads()):
        return ref, sec
    # no recorded time, or recorded with another thread count: time it here
    t0 = time.perf_counter()
    ref = render_reference(scene, frame, bounces=bounces, spp=spp, seed=seed, spp_side=spp_side, use_cache=False)
    wall = time.perf_counter() - t0
    return ref, reference_seconds(ref) or wall  # the renderer's own split excludes export, load and compilation


def make_exposure(ref, mask):
    """Display exposure fixed per scene (``references.metrics.Exposure.from_reference``)."""
    from references.metrics import Exposure

    return Exposure.from_reference(ref, mask)


def all_metrics(img, ref, mask, *, exposure=None) -> dict:
    from references.metrics import all_metrics as _m

    return _m(img, ref, mask, exposure=exposure)


def geometry(scene, frame):
    g = scene.geometry(getattr(frame, "pose", None))
    return g.V, g.F


def is_dynamic(scene) -> bool:
    return getattr(scene, "skeleton", None) is not None
