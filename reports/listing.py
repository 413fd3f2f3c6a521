"""``run_bench.py list``: what can be run, without reading code — scenes (vertex counts at both
sizes, env map, articulated or not), methods (capabilities), suites, sequence kinds and studies."""
from __future__ import annotations

from methods.registry import available_methods, get_method
from methods.studies import STUDIES
from reports.suites import SUITES
from scenes import library, sequences

KIND_TEXT = {
    "V": "view orbits; lighting and materials fixed (Sun 2007 Table 1 'V')",
    "VB": "view + material parameters change ('V&B')",
    "VBL": "view + materials + env map spins about +Y ('V,B&L')",
    "P": "pose animation (articulated scenes)",
    "L": "lighting only: env map rotates about a seeded tilted axis",
    "E": "lighting only: a different captured probe every frame",
    "VL": "view + lighting rotation, materials fixed",
}


def _env_name(scene) -> str:
    return getattr(scene.envmap, "name", None) or f"{scene.envmap.height}×{scene.envmap.width}"


def scene_lines(sizes=("test", "bench")) -> list[str]:
    out = [f"{'scene':14s} " + " ".join(f"{s + ' verts':>11s}" for s in sizes) + f"  {'env map':12s} articulated  regions"]
    for name in library.SCENES:
        scenes = [library.get_scene(name, s) for s in sizes]
        counts = " ".join(f"{int(sc.geometry().V.shape[0]):11d}" for sc in scenes)
        sc = scenes[0]
        env = _env_name(sc)
        out.append(f"{name:14s} {counts}  {env:12s} {'yes' if sc.skeleton is not None else 'no':11s}  "
                   + ", ".join(f"{r}: {m.kind}" for r, m in sc.materials.items()))
    return out


def method_lines() -> list[str]:
    out = [f"{'method':15s} {'lighting':8s} {'BRDFs':6s} {'geometry':8s} {'bounces':7s} families"]
    for name in available_methods():
        c = get_method(name).capabilities
        out.append(f"{name:15s} {'dynamic' if c.dynamic_lighting else 'fixed':8s} "
                   f"{'dynamic' if c.dynamic_brdf else 'fixed':6s} {'dynamic' if c.dynamic_geometry else 'static':8s} "
                   f"{c.max_bounces:<7d} {', '.join(sorted(c.brdfs))}")
    return out


def suite_lines() -> list[str]:
    out = []
    for name, s in SUITES.items():
        scenes = ", ".join(s.scenes) if s.scenes else "every library scene"
        out.append(f"{name:8s} size {s.size}, kinds {'/'.join(s.kinds)} (+{'/'.join(s.dynamic_kinds)} if articulated), "
                   f"{s.n_frames} frames, {s.ref_spp}-spp references; scenes: {scenes}")
    return out


def catalogue(*, sizes=("test", "bench")) -> str:
    """The whole listing as text."""
    parts = ["Scenes (scenes/library.py; a TOML scene file runs with --scene-file):", *scene_lines(sizes), "",
             "Methods (capabilities: what each claims; other cells are n/a):", *method_lines(), "",
             "Suites (run_bench.py run --suite NAME):", *suite_lines(), "",
             "Sequence kinds:", *(f"{k:4s} {v}" for k, v in KIND_TEXT.items() if k in sequences.KINDS), "",
             "Studies (run_bench.py study NAME):",
             *(f"{n:28s} {st.paper or 'cross-method'}" for n, st in sorted(STUDIES.items()))]
    return "\n".join(parts)
