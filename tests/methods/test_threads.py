"""Results do not depend on the thread count (issue 17: a local run with 2 threads and a process
pool with 1 thread per worker must give the same numbers): every registered method, precompute and
render, with 1 and with 2 torch (and Dr.Jit) threads, bit for bit.

What this caught (fixed as ``methods.core.threads`` describes): in-out's and PTT's BRDF SVDs
picked different singular vectors inside degenerate singular spaces (max pixel difference 0.31 and
0.019 on sphere_plane); PTT's PCA-basis and CTA-compression eigh, the CPCA SVD and its error sum,
and a bmm of non-contiguous batches in the one-bounce transport rounded differently; ZH's lstsq of
its monomial → SH map (LAPACK gelsy) differed even between two calls. That map is cached per
process (``functools.lru_cache``), so every method cache is cleared before each run: a value
computed once, with the first thread count, would hide a difference."""
from __future__ import annotations

import sys

import pytest
import torch

from methods.core.threads import torch_threads
from methods.registry import get_method
from references.gbuffer import make_gbuffer
from scenes.library import get_scene
from scenes.sequences import make_sequence
from testing.small_configs import CASES, project_methods



def test_every_method_is_covered():
    assert {m for m, _, _ in CASES.values()} == project_methods()


def _clear_method_caches() -> None:
    """Empty every ``functools`` cache of the ``methods`` packages (module-level functions)."""
    for name, mod in list(sys.modules.items()):
        if name.startswith("methods.") and mod is not None:
            for obj in list(vars(mod).values()):
                if callable(getattr(obj, "cache_clear", None)) and hasattr(obj, "cache_info"):
                    obj.cache_clear()


def _state(obj, prefix: str = "m", depth: int = 0, seen=None):
    """(name, tensor) of every tensor a method keeps (attributes, dicts, lists, dataclasses)."""
    seen = set() if seen is None else seen
    if id(obj) in seen or depth > 6:
        return
    seen.add(id(obj))
    if isinstance(obj, torch.Tensor):
        yield prefix, (obj.to_dense() if obj.layout != torch.strided else obj)
    elif isinstance(obj, dict):
        for k, v in obj.items():
            yield from _state(v, f"{prefix}[{k!r}]", depth + 1, seen)
    elif isinstance(obj, (list, tuple)):
        for i, v in enumerate(obj):
            yield from _state(v, f"{prefix}[{i}]", depth + 1, seen)
    elif hasattr(obj, "__dict__") and type(obj).__module__.startswith("methods"):
        for k, v in vars(obj).items():
            yield from _state(v, f"{prefix}.{k}", depth + 1, seen)


def _dr_threads(n: int | None):
    import drjit as dr

    old = dr.thread_count()
    if n is not None:
        dr.set_thread_count(n)
    return old


@pytest.mark.parametrize("case", sorted(CASES))
def test_bit_identical_with_one_and_two_threads(case):
    name, scene_name, config = CASES[case]
    scene = get_scene(scene_name, "test")
    caps = get_method(name)(**config).capabilities
    # view and lighting change (with the BRDFs where the method allows it), then the pose where
    # the scene is skinned and the method follows it, else swapped probes
    first = "VBL" if caps.why_not(scene, "VBL", 0) is None else "L"
    posed = scene.skeleton is not None and caps.why_not(scene, "P", 0) is None
    kinds = [first, "P" if posed else "E"]
    frames = [f for k in kinds for f in make_sequence(scene, k, 2, 0)]
    gbuffers = [make_gbuffer(scene, f, 1) for f in frames]
    runs = []
    dr_before = _dr_threads(None)
    try:
        for t in (1, 2):
            _clear_method_caches()
            _dr_threads(t)
            with torch_threads(t):
                m = get_method(name)(**config)
                m.precompute(scene)
                imgs = [m.render(f, g) for f, g in zip(frames, gbuffers)]
            runs.append((dict(_state(m)), imgs))
    finally:
        _dr_threads(dr_before)
    (s1, imgs1), (s2, imgs2) = runs
    assert s1.keys() == s2.keys()
    differ = {k: float((s1[k].double() - s2[k].double()).abs().max()) if s1[k].is_floating_point() else -1.0
              for k in s1 if not (s1[k].shape == s2[k].shape and torch.equal(s1[k], s2[k]))}
    assert not differ, f"precomputed state depends on the thread count: {differ}"
    for i, (a, b) in enumerate(zip(imgs1, imgs2)):
        assert torch.equal(a, b), f"frame {i}: max |difference| {float((a - b).abs().max())}"
