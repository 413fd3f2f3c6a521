"""Env map → cube map resampling per lighting change (issue 14): the fast `cubemap.from_envmap`
against its oracle `cubemap.from_radiance` (same sub-samples, weights and look-ups).

    python -m benchmarks.cube_resample                   # ms per call, N = 16 / 32, 256 × 512 probe
    python -m benchmarks.cube_resample --threads 1
    python -m benchmarks.cube_resample --prefilter       # + the error a 2× box prefilter would add
    python -m benchmarks.cube_resample --threads 1 --no-calls --base OTHER_CHECKOUT   # its from_envmap vs this one's

Per (N, supersample): the median wall ms of ``--repeats`` calls of each path after one warm-up
call, the two paths *alternating call by call in one process* (the machine is shared: the ratio is
taken under the same load; the load average is printed; process CPU ms beside the wall ms: at
one thread on a shared machine roughly what an unshared core would take), the map rotated anew before every
call (an L frame: nothing keyed on the rotation is reused), and their largest relative texel
difference. Also the compiled per-sample loop alone (all 393k sub-samples of the N = 16 cube, per-texel sums included: ns per
sample) — what bounds a call: 6·N²·s² = 393k sub-samples (s = max(s, `min_supersample`)), each a
rotation, an atan2, an acos and 4 gathers × 3 channels.

``--prefilter`` answers idea (a) of the brief: box-downsample the map by 2 first
(`EnvMap.box_downsampled`) so that `min_supersample` follows the halved map (4× fewer sub-samples):
its per-texel relative error and the irradiance error on the 6 axis normals against the converged
texel means (s = 64, computed with the fast path), on a 2 × 2-texel sun and on the smooth
``overcast`` map; next to the same errors of the unfiltered path.
"""
from __future__ import annotations

import argparse
import math
import os
import statistics
import time

import torch


def _rotations(n: int, seed: int = 0):
    from scenes.sequences import rotation_axis_angle

    g = torch.Generator().manual_seed(seed)
    for _ in range(n):
        axis = torch.randn(3, generator=g, dtype=torch.float64)
        yield rotation_axis_angle((axis / axis.norm()).tolist(), float(torch.rand((), generator=g)) * 2 * math.pi)


def time_calls(env, N: int, s: int, repeats: int) -> dict:
    from methods.core import cubemap as cm

    fast = cm.from_envmap(env, N, supersample=s)  # warm-up (compiles once per map size)
    ref = cm.from_radiance(env.radiance, N, supersample=s, source_res=env.height)
    rel = float(((fast - ref).abs() / ref.abs().clamp_min(1e-30)).max())
    t_ref, t_fast, c_ref, c_fast = [], [], [], []
    for R in _rotations(repeats, seed=N * 100 + s):
        e = env.rotated(R)
        t0, c0 = time.perf_counter(), time.process_time()
        cm.from_radiance(e.radiance, N, supersample=s, source_res=e.height)
        t1, c1 = time.perf_counter(), time.process_time()
        cm.from_envmap(e, N, supersample=s)
        t2, c2 = time.perf_counter(), time.process_time()
        t_ref.append(t1 - t0)
        t_fast.append(t2 - t1)
        c_ref.append(c1 - c0)
        c_fast.append(c2 - c1)
    s_eff = max(s, cm.min_supersample(N, env.height))
    return {"N": N, "s": s, "s_eff": s_eff, "samples": 6 * N * N * s_eff * s_eff,
            "oracle_ms": 1e3 * statistics.median(t_ref), "fast_ms": 1e3 * statistics.median(t_fast),
            "oracle_cpu_ms": 1e3 * statistics.median(c_ref), "fast_cpu_ms": 1e3 * statistics.median(c_fast),
            "max_rel_diff": rel}


def time_base(env, base: str, N: int, s: int, repeats: int) -> dict:
    """``from_envmap`` of the checkout at ``base`` (its ``methods/core/cubemap.py`` loaded beside this
    one, `benchmarks.common.load_file_module`) against this checkout's, alternating call by call (the
    first two calls untimed), the map rotated anew before every call: median wall / process-CPU ms
    and the largest relative texel difference."""
    import os as _os

    from benchmarks.common import load_file_module
    from methods.core import cubemap as cm

    old = load_file_module(_os.path.join(base, "methods", "core", "cubemap.py"), "base_cubemap")
    t = {"base": ([], []), "new": ([], [])}
    rel = 0.0
    for i, R in enumerate(_rotations(repeats + 2, seed=N * 100 + s)):
        e = env.rotated(R)
        out = {}
        for k in (("base", "new") if i % 2 else ("new", "base")):
            mod = old if k == "base" else cm
            t0, c0 = time.perf_counter(), time.process_time()
            out[k] = mod.from_envmap(e, N, supersample=s)
            if i >= 2:
                t[k][0].append(time.perf_counter() - t0)
                t[k][1].append(time.process_time() - c0)
        rel = max(rel, float(((out["base"] - out["new"]).abs() / out["base"].abs().clamp_min(1e-30)).max()))
    r = {f"{k}_{w}_ms": 1e3 * statistics.median(v[j]) for k, v in t.items() for j, w in enumerate(("wall", "cpu"))}
    return {"N": N, "s": s, **r, "max_rel_diff": rel}


def time_block(env, repeats: int) -> float:
    """ns per sub-sample of the compiled loop (`cubemap._texel_sums`: look-ups and per-texel sums) on
    the in-out cube (N = 16, s = 16: 393k sub-samples, one block)."""
    from methods.core import cubemap as cm

    N, s = 16, 16
    d, w = cm._subsample_table(N, s)
    args = (*(t.view(6 * N * N, s * s) for t in (d[0], d[1], d[2], w)), env.to_world.float(),
            env.periodic_texels(None, torch.float32, planes=True), env.height, env.width)
    cm._texel_sums_fused(*args)
    ts = []
    for _ in range(max(repeats, 7) * 3):
        t0 = time.perf_counter()
        cm._texel_sums_fused(*args)
        ts.append(time.perf_counter() - t0)
    return 1e9 * statistics.median(ts) / (6 * N * N * s * s)


def prefilter_errors(N: int = 16, s: int = 4) -> list[dict]:
    """Errors against the converged texel means of the unfiltered and the 2×-prefiltered path."""
    from methods.core import cubemap as cm
    from scenes.envmap import EnvMap, procedural

    d = cm.texel_directions(N, dtype=torch.float64)
    w = cm.texel_solid_angles(N, dtype=torch.float64)
    cos = (d[..., None, :] * torch.eye(3, dtype=torch.float64)).sum(-1).clamp_min(0)
    irr = lambda c: torch.einsum("fijc,fija,fij->ac", c.double(), cos, w)  # noqa: E731
    gen = torch.Generator().manual_seed(4)
    maps = []
    for i in range(4):
        data = torch.full((256, 512, 3), 0.2)
        r, c = int(torch.randint(20, 110, (1,), generator=gen)), int(torch.randint(0, 510, (1,), generator=gen))
        data[r:r + 2, c:c + 2] = 5.0e4
        maps.append((f"sun {i}", EnvMap(data).rotated(next(_rotations(1, seed=i)))))
    maps.append(("overcast 256", procedural("overcast", height=256, seed=2).rotated(next(_rotations(1, seed=9)))))
    out = []
    for name, env in maps:
        conv = cm.from_envmap(env, N, supersample=64)  # converged (the oracle's sub-sampling at 64²)
        ic = irr(conv)
        lit = ic > 0.05 * ic.max()
        big = conv.sum(-1) > 0.01 * conv.sum(-1).max()  # texels carrying the light
        row = {"map": name}
        for tag, e in (("full", env), ("box2", env.box_downsampled(2))):
            c = cm.from_envmap(e, N, supersample=s)
            rel = ((c - conv).abs() / conv.abs().clamp_min(1e-30)).amax(-1)
            row[tag] = {"texel_rel_max": float(rel[big].max()),
                        "texel_rel_mean": float(rel.mean()),
                        "irradiance_rel_max": float((((irr(c) - ic).abs() / ic)[lit]).max()),
                        "energy_rel": float(cm.integrate(c.permute(3, 0, 1, 2).double()).sum()
                                            / cm.integrate(conv.permute(3, 0, 1, 2).double()).sum() - 1)}
        out.append(row)
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=9)
    ap.add_argument("--probe", default="courtyard")
    ap.add_argument("--prefilter", action="store_true")
    ap.add_argument("--frames", type=int, default=0, help="also time method frames (old vs new), this many per kind")
    ap.add_argument("--methods", nargs="+", default=["inout", "ptt"])
    ap.add_argument("--scene", default="sphere_plane")
    ap.add_argument("--size", default="bench")
    ap.add_argument("--kinds", nargs="+", default=["L", "E"])
    ap.add_argument("--no-calls", action="store_true", help="skip the per-call timings")
    ap.add_argument("--base", default=None, help="also time from_envmap of this checkout against this one's")
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    from scenes.envmap import probe

    env = probe(a.probe)
    print(f"load: {os.getloadavg()[0]:.2f} {os.getloadavg()[1]:.2f}  threads {a.threads}  map {env.height}x{env.width}")
    for N, s in (() if a.no_calls else ((16, 4), (32, 2))):
        r = time_calls(env, N, s, a.repeats)
        print(f"N={r['N']:3d} s={r['s']} (→{r['s_eff']}, {r['samples']} sub-samples): oracle {r['oracle_ms']:7.1f} ms"
              f"  fast {r['fast_ms']:6.2f} ms  ratio {r['oracle_ms'] / r['fast_ms']:5.1f}×  (process CPU: oracle"
              f" {r['oracle_cpu_ms']:.1f} ms, fast {r['fast_cpu_ms']:.2f} ms, {r['oracle_cpu_ms'] / r['fast_cpu_ms']:.1f}×)"
              f"  max rel diff {r['max_rel_diff']:.2e}")
    if not a.no_calls:
        print(f"compiled loop: {time_block(env, a.repeats):.2f} ns per sub-sample (one block, {a.threads} threads)")
        print(f"load after: {os.getloadavg()[0]:.2f}")
    if a.base:
        for N, s in ((16, 4), (32, 2)):
            r = time_base(env, a.base, N, s, a.repeats)
            print(f"N={N:3d} s={s} base {a.base}: CPU {r['base_cpu_ms']:.2f} -> {r['new_cpu_ms']:.2f} ms "
                  f"({r['base_cpu_ms'] / r['new_cpu_ms']:.2f}x), wall {r['base_wall_ms']:.2f} -> {r['new_wall_ms']:.2f} ms "
                  f"({r['base_wall_ms'] / r['new_wall_ms']:.2f}x), max rel diff {r['max_rel_diff']:.2e}")
    if a.frames:
        frames_ab(a.methods, a.scene, a.size, a.kinds, a.frames, {"ptt": {"light_res_1": 4}})
    if a.prefilter:
        for row in prefilter_errors():
            print(row["map"], *(f"{k}: texel rel max {v['texel_rel_max']:.3f} mean {v['texel_rel_mean']:.4f}"
                                 f" irradiance {v['irradiance_rel_max']:.4f} energy {v['energy_rel']:+.4f}"
                                 for k, v in row.items() if k != "map"), sep="\n  ")



def frames_ab(methods, scene_name: str, size: str, kinds, n_frames: int, configs: dict) -> list[dict]:
    """Frame times of each method with the fast resampling ("new") and with the oracle
    `from_radiance` patched in for `from_envmap` ("old", the code before), two instances sharing
    one precomputation (the second comes from the precompute cache), frame by frame alternating
    which goes first; frame 0 of each sequence (caches, compilation) is not timed. Wall and process
    CPU ms medians."""
    from benchmarks.common import precomputed, setup
    from methods.core import cubemap as cm
    from methods.registry import get_method

    fast_fn = cm.from_envmap

    def oracle_fn(envmap, N, *, supersample=4, dtype=torch.float32):
        return cm.from_radiance(envmap.radiance, N, supersample=supersample, source_res=envmap.height, dtype=dtype)

    scene, _, _, _ = setup(scene_name, size, kind="V", n_frames=1)
    rows = []
    for name in methods:
        cls = get_method(name)
        cls = cls if isinstance(cls, type) else type(cls)
        cfg = configs.get(name, {})
        inst = {"old": precomputed(cls, scene, cfg)[0], "new": precomputed(cls, scene, cfg)[0]}
        for kind in kinds:
            _, frames, gbs, _ = setup(scene, size, kind=kind, n_frames=n_frames, seed=1)
            t = {"old": ([], []), "new": ([], [])}
            diff = 0.0
            for i, (f, g) in enumerate(zip(frames, gbs)):
                imgs = {}
                for which in (("old", "new") if i % 2 == 0 else ("new", "old")):
                    cm.from_envmap = oracle_fn if which == "old" else fast_fn
                    try:
                        t0, c0 = time.perf_counter(), time.process_time()
                        imgs[which] = inst[which].render(f, g)
                        w, c = time.perf_counter() - t0, time.process_time() - c0
                    finally:
                        cm.from_envmap = fast_fn
                    if i > 0:
                        t[which][0].append(w)
                        t[which][1].append(c)
                diff = max(diff, float((imgs["old"] - imgs["new"]).abs().max() / imgs["old"].abs().max().clamp_min(1e-30)))
            row = {"method": name, "scene": scene_name, "kind": kind, "frames": n_frames - 1, "max_rel_pixel_diff": diff}
            for which in ("old", "new"):
                row[f"{which}_wall_ms"] = 1e3 * statistics.median(t[which][0])
                row[f"{which}_cpu_ms"] = 1e3 * statistics.median(t[which][1])
            rows.append(row)
            print(f"{name:6} {scene_name} {kind:2}: old {row['old_wall_ms']:7.1f} ms (cpu {row['old_cpu_ms']:7.1f})"
                  f"  new {row['new_wall_ms']:7.1f} ms (cpu {row['new_cpu_ms']:7.1f})"
                  f"  ratio {row['old_wall_ms'] / row['new_wall_ms']:4.2f} (cpu {row['old_cpu_ms'] / row['new_cpu_ms']:4.2f})"
                  f"  max |old−new|/max {diff:.1e}  load {os.getloadavg()[0]:.1f}", flush=True)
    return rows


if __name__ == "__main__":
    main()
