"""Sun et al. 2007 figures as studies: Fig. 5 (BRDF tensor error over n_h × n_ωi, with and without
lobe separation), Fig. 6 (error per sampled BRDF for 0–4 lobes), Fig. 8 (lighting resolution of the
one-bounce PTT), Figs. 9–10 (clustered tensor approximation of T¹: tensor error and rendered images
vs eigenvectors / lighting dimension), and PTT's row of the terms-vs-exponent study
(`reports.studies`).

Every figure is a function returning a ``pandas.DataFrame``; given ``out_dir`` it also writes
``<fig>.csv`` and ``<fig>.png`` there. Each is registered as a study (defaults sized for a
2-core machine; ``--quick``: a few cells each, seconds)::

    python run_bench.py study sun-fig5      # Cook-Torrance and Blinn-Phong spaces, DiskGrid(24)
    python run_bench.py study sun-fig6
    python run_bench.py study sun-fig8      # 5 precomputes
    python run_bench.py study sun-fig9      # tensor errors from one dense precompute
    python run_bench.py study sun-fig10     # 9 precomputes
    python run_bench.py study ptt-terms
    python run_bench.py study ptt-figures   # all of the above into one folder

Other scenes, reference spp, PTT settings or ``images=True`` (Fig. 9 renders): call the
functions from Python.

Image figures: scene ``alcove`` (test size), the first frame of its "V" sequence, a 2-spp
G-buffer, PTT with ``BASE_CONFIG`` (the settings of ``tests/methods/ptt/test_method.py``), scored
on the Mitsuba reference's coverage mask against `references.render.render_reference` with
``bounces=1`` (direct + one bounce, the +1 column of Sun Fig. 11). "indirect" is the +1-bounce
part alone: PTT ``with_bounces(1) − with_bounces(0)`` against Mitsuba ``bounces=1 − bounces=0``
(same seeds, so the direct-lighting noise largely cancels; its own floor from the two halves).

Fig. 5's error measure ("squared error", normalisation not stated in the paper): ``rel_sq_err`` =
‖F − F̂‖²_F / ‖F‖²_F with F the *unseparated* specular tensor (`brdf_tensor.brdf_tensor`) and
F̂ = F_s + Tucker(F_r) (F_s is exact), plus the absolute ``sse`` and per-entry ``mse``; the grid
over (n_h, n_ω) comes from one HOSVD (`brdf_tensor.hosvd_error_grid`).

Terms-vs-exponent (Sun 2007 eq. 2, §4.1, §4.3): for Blinn–Phong shininess s the BRDF tensor of
ONE material, F[h, ωo, ωi] with N_h = 1 (ks = 1, no cosine, `brdf_tensor.DiskGrid(TERMS_GRID_N)`
for ωo and ωi), is Tucker-factorised with n_h = 1 and n_ωo = n_ωi = n_ω (§4.3 "we set n_ωo to be
equal to n_ωi"; for N_h = 1 the truncated HOSVD is the rank-n_ω truncated SVD, the optimum). The
reported terms are **n_ωi**: the number of incidence components E_x(k) every vertex carries at run
time (eq. 3's k), i.e. what a shinier material costs per vertex. Error measure: Fig. 5's
``rel_sq_err`` = ‖F − F̂‖²/‖F‖², F *unseparated*, F̂ = F_s + Tucker(F_r) with separation
(`brdf_tensor.separate_tensor`, lobes 0°/7°/14°/21°; the lobes are stored beside the tensor —
four per-vertex fractional visibilities — and are not counted in the terms; the note says so).
Two contributors: ``ptt`` (no separation) and ``ptt_separated``.

The measured numbers of every figure are in the README ("PTT figures") and pinned in
tests/methods/ptt/test_ptt_study.py; they are not repeated here.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch
from torch import Tensor

from methods.core import tensors as T
from methods.ptt.brdf_space import BRDFSpace, get_space
from methods.ptt.brdf_tensor import (DEFAULT_RANKS, DiskGrid, brdf_tensor, fit_brdf_tensor, hosvd_error_grid,
                                     separate_tensor)
from methods.ptt.lobes import LOBE_DEGREES
from methods.studies import Study, TermsRecord, register_study, register_term_ladder, register_terms_contributor
from methods.studies import pyplot as _pyplot
from methods.studies import save_fig as _save

__all__ = [
    "BASE_CONFIG",
    "FIG8_LIGHT_RES",
    "FIG9_EIGENVECTORS",
    "FIG9_LIGHT_DIMS",
    "FIG10_COMBOS",
    "FIG5_N_H",
    "FIG5_N_OMEGA",
    "FIG5_N_OMEGA_PAPER",
    "PAPER_FIG5_NO_SEPARATION",
    "REF_SPP",
    "TERMS_EXPONENTS",
    "TERMS_GRID_N",
    "TERMS_TARGET",
    "TERMS_TARGET_KIND",
    "fig5_grid",
    "plot_fig5",
    "fig5",
    "fig6_lobe_study",
    "fig8_lighting_resolution",
    "fig9_tensor_error",
    "fig10_compression_images",
    "tensor_error_curve",
    "terms_needed",
    "terms_needed_separated",
    "terms_study",
    "run_all",
]

# PTT settings of the image figures (those of tests/methods/ptt/test_method.py: 64 hemisphere rays,
# 6×16×16 direct cube map; everything else the PTT defaults).
BASE_CONFIG: dict[str, Any] = dict(rays=64, cube_res=16)
# Mitsuba reference samples per pixel (the Fig. 11 test's; cached on disk after the first run).
REF_SPP = 256
# G-buffer samples per pixel for the image figures.
GBUFFER_SPP = 2

# Sun 2007 Fig. 8 shows 6×4×4, 6×8×8, 6×16×16; we add 1 and 2 to see where the error flattens.
FIG8_LIGHT_RES: tuple[int, ...] = (1, 2, 4, 8)
# Fig. 9 axes (None = full rank: every vertex of a cluster / every lighting coefficient).
FIG9_EIGENVECTORS: tuple[int | None, ...] = (1, 4, 8, 16, 32, 64, 128, None)
FIG9_LIGHT_DIMS: tuple[int | None, ...] = (1, 4, 8, 16, 32, 64, 96, 128, None)
# Sun 2007 Fig. 10: eigenvectors / lighting dimension 8/64, 16/64, 32/16, 32/32, 32/64, 32/96,
# 64/64, ground truth (= full rank here: must reproduce the dense image).
FIG10_COMBOS: tuple[tuple[int | None, int | None], ...] = (
    (8, 64), (16, 64), (32, 16), (32, 32), (32, 64), (32, 96), (64, 64), (None, None))

# Lower clip of log-scale error plots (full-rank errors are float round-off).
PLOT_FLOOR = 1e-6

# Terms-vs-exponent: the study's Blinn–Phong ladder (reports.studies.TermsStudyConfig.table_exponents),
# the disk grid (812 directions; the counts at s <= 128 change by <= 1-2 terms at 48, 1804 directions),
# and the accuracy target (relative squared error 1 % = 10 % relative Frobenius error).
TERMS_EXPONENTS: tuple[float, ...] = (1, 2, 4, 8, 16, 32, 64)
TERMS_GRID_N = 32
TERMS_TARGET = 0.01
TERMS_TARGET_KIND = ("relative squared error ||F-F^||^2/||F||^2 of the Blinn-Phong BRDF tensor "
                     f"(1 BRDF, DiskGrid {TERMS_GRID_N}, n_wo = n_wi) -> n_wi")


# -- Fig. 5 (BRDF tensor error) -------------------------------------------------------------------

FIG5_N_H: tuple[int, ...] = (1, 2, 3, 4, 5, 6)
FIG5_N_OMEGA: tuple[int, ...] = (4, 8, 16, 32)
FIG5_N_OMEGA_PAPER: tuple[int, ...] = (4, 8, 12, 16, 20, 24, 28, 32)  # §4.3's full sweep
# §4.1: "the squared error of tensor approximation without specular lobe separation is 0.952465"
# (n_h = 6, n_ωi = 32, 100 Cook–Torrance fits of MERL materials).
PAPER_FIG5_NO_SEPARATION = 0.952465


def fig5_grid(space: BRDFSpace | str = "ct", *, grid_n: int = 24, n_h: Sequence[int] = FIG5_N_H,
              n_omega: Sequence[int] = FIG5_N_OMEGA, separation: Sequence[bool] = (False, True),
              degrees: Sequence[float] = LOBE_DEGREES, method: str = "hosvd",
              hooi_iters: int = 20, progress: bool = False):
    """Sun 2007 Fig. 5: tensor approximation error over n_h × n_ωi (n_ωo = n_ωi), with and without
    lobe separation.

    Args:
        space: "ct", "bp" or a `BRDFSpace`; grid_n: `DiskGrid` resolution (N ≈ π grid_n²/4 must
            be ≥ max(n_omega)); method: "hosvd" (all cells from one HOSVD, fast) or "hooi"
            (one HOSVD-initialised HOOI per cell via `methods.core.tensors.tucker`; slow for
            grid_n ≳ 24); progress: tqdm bar.
    Returns:
        pandas.DataFrame, one row per (separated, n_h, n_omega), columns: space, grid_n, N_omega,
        N_h, separated, n_h, n_omega, method, rel_sq_err (‖F − F̂‖²/‖F‖², F unseparated),
        sse (‖F − F̂‖²), mse (sse / F.numel()).
    """
    import pandas as pd
    from tqdm import tqdm

    space = get_space(space) if isinstance(space, str) else space
    grid = DiskGrid(grid_n)
    if max(n_omega) > grid.N or max(n_h) > space.n_h:
        raise ValueError(f"ranks exceed the tensor ({space.n_h}, {grid.N}, {grid.N})")
    if method not in ("hosvd", "hooi"):
        raise ValueError(f"method must be 'hosvd' or 'hooi', got {method!r}")
    F = brdf_tensor(space, grid)
    norm2 = float(F.square().sum())
    rows = []
    for sep in tqdm(list(separation), desc="fig5", disable=not progress):
        X = separate_tensor(F, grid, degrees=degrees)[0] if sep else F
        if method == "hosvd":
            errs = hosvd_error_grid(X, n_h, n_omega)
        else:
            errs = {}
            for a in n_h:
                for b in n_omega:
                    D, U = fit_brdf_tensor(X, (a, b, b), method="hooi", n_iter_max=hooi_iters)
                    errs[(a, b)] = float((X - T.tucker_reconstruct(D, U)).square().sum())
        for (a, b), e in errs.items():
            rows.append(dict(space=space.kind, grid_n=grid_n, N_omega=grid.N, N_h=space.n_h,
                             separated=bool(sep), n_h=a, n_omega=b, method=method,
                             rel_sq_err=e / norm2, sse=e, mse=e / F.numel()))
    return pd.DataFrame(rows)


def plot_fig5(df, out_dir: str | Path, *, stem: str = "fig5") -> list[Path]:
    """Write Fig. 5 plots (matplotlib Agg) to `out_dir`: one log-scale heatmap of rel_sq_err over
    (n_h, n_ω) per (space, separated), and the paper-style curves (error vs n_ωi, one curve per
    n_h). Returns the PNG paths."""
    from matplotlib.colors import LogNorm

    plt = _pyplot()

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for (kind, sep), g in df.groupby(["space", "separated"]):
        tab = g.pivot(index="n_h", columns="n_omega", values="rel_sq_err").sort_index()
        fig, ax = plt.subplots(1, 2, figsize=(10, 4))
        vals = tab.to_numpy()
        im = ax[0].imshow(vals, origin="lower", aspect="auto",
                          norm=LogNorm(vmin=max(vals.min(), 1e-12), vmax=max(vals.max(), 1e-11)))
        ax[0].set_xticks(range(tab.shape[1]), [str(c) for c in tab.columns])
        ax[0].set_yticks(range(tab.shape[0]), [str(r) for r in tab.index])
        for (r, c), v in np.ndenumerate(vals):
            ax[0].text(c, r, f"{v:.2g}", ha="center", va="center", fontsize=7,
                       color="k" if im.norm(v) > 0.6 else "w")
        ax[0].set_xlabel("n_ωi = n_ωo")
        ax[0].set_ylabel("n_h")
        fig.colorbar(im, ax=ax[0], label="‖F − F̂‖² / ‖F‖²")
        for r in tab.index:
            ax[1].plot(tab.columns, tab.loc[r], marker="o", label=f"n_h={r}")
        ax[1].set_yscale("log")
        ax[1].set_xlabel("n_ωi")
        ax[1].set_ylabel("relative squared error")
        ax[1].legend(fontsize=7)
        title = f"Sun 2007 Fig. 5 — {kind.upper()} {'with' if sep else 'without'} lobe separation"
        fig.suptitle(title)
        fig.tight_layout()
        p = out / f"{stem}_{kind}_{'sep' if sep else 'nosep'}.png"
        fig.savefig(p, dpi=110)
        plt.close(fig)
        paths.append(p)
    return paths


def fig5(out_dir: str | Path, space: BRDFSpace | str = "ct", **kw):
    """`fig5_grid(space, **kw)`, then write `fig5_<space>.csv` and the PNGs of `plot_fig5` into
    `out_dir`. Returns the DataFrame."""
    df = fig5_grid(space, **kw)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    kind = df["space"].iloc[0]
    df.to_csv(out / f"fig5_{kind}.csv", index=False)
    plot_fig5(df, out)
    return df


# -- Fig. 6 (numeric form) -----------------------------------------------------------------------


def fig6_lobe_study(space: BRDFSpace | str = "bp", *, grid_n: int = 16, ranks: Sequence[int] | None = None,
                    lobe_sets: Sequence[Sequence[float]] = ((), (0.0,), (0.0, 7.0), (0.0, 7.0, 14.0),
                                                            (0.0, 7.0, 14.0, 21.0)),
                    method: str = "hosvd"):
    """Sun 2007 Fig. 6 as numbers: tensor-BRDF error per sampled BRDF for 0–4 lobe components
    ("a greater number of lobe components leads to better approximations").

    Returns:
        pandas.DataFrame with columns space, grid_n, lobes (e.g. "0,7"), n_lobes, h, param (the
        BRDF's parameters), rel_sq_err (‖F_h − F̂_h‖²/‖F_h‖² of that BRDF) and total_rel_sq_err
        (over the whole space), at `ranks` (default `DEFAULT_RANKS[space.kind]`).
    """
    import pandas as pd

    space = get_space(space) if isinstance(space, str) else space
    grid = DiskGrid(grid_n)
    ranks = tuple(DEFAULT_RANKS[space.kind] if ranks is None else ranks)
    F = brdf_tensor(space, grid)
    nF = F.square().sum((1, 2))
    rows = []
    for degs in lobe_sets:
        X = separate_tensor(F, grid, degrees=degs)[0] if len(degs) else F
        D, U = fit_brdf_tensor(X, ranks, method=method)
        e = (X - T.tucker_reconstruct(D, U)).square().sum((1, 2))
        tot = float(e.sum() / nF.sum())
        for h, mat in enumerate(space.materials):
            par = {k: v for k, v in mat.params().items() if k in ("s", "m", "F0")}
            rows.append(dict(space=space.kind, grid_n=grid_n, lobes=",".join(f"{k:g}" for k in degs),
                             n_lobes=len(degs), h=h, param=par, rel_sq_err=float(e[h] / nF[h]),
                             total_rel_sq_err=tot))
    return pd.DataFrame(rows)


# -- shared set-up of the image figures --------------------------------------------------------


@dataclass
class _Setup:
    scene: Any
    frame: Any
    gbuffer: Any
    ref0: Any      # references.render.Reference, bounces=0
    ref1: Any      # bounces=1
    mask: Tensor   # (H, W) bool: reference coverage & G-buffer coverage
    indirect_floor: float


def _setup(scene_name: str, size: str, spp: int, seed: int = 0) -> _Setup:
    """Scene, first "V" frame, 2-spp G-buffer, Mitsuba references (0 and 1 bounce) and mask."""
    from references.metrics import rmse
    from references.setup import frame_setup
    from scenes.library import get_scene

    _check_pos("spp", spp)
    su = frame_setup(get_scene(scene_name, size), kind="V", n_frames=1, seed=seed, spp_side=GBUFFER_SPP,
                     ref_spp=spp, bounces=(0, 1))
    r0, r1 = su.references[0], su.references[1]
    mask = su.mask(0)
    # noise floor of the indirect reference r1 − r0 from its two independent halves
    floor = rmse(r1.half_a - r0.half_a, r1.half_b - r0.half_b, mask) / 2
    return _Setup(su.scene, su.frame, su.gbuffer, r0, r1, mask, floor)


def _check_pos(name: str, v: Any) -> int:
    if isinstance(v, bool) or not isinstance(v, int) or v < 1:
        raise ValueError(f"{name} must be a positive int, got {v!r}")
    return v


def _ptt(scene, **config):
    """A precomputed one-bounce PTT (public constructor + precompute only)."""
    from methods.ptt.method import PTT

    cfg = dict(BASE_CONFIG, bounces=1, **config)
    m = PTT(**cfg)
    t = time.perf_counter()
    m.precompute(scene)
    return m, time.perf_counter() - t


def _images(m, st: _Setup) -> tuple[Tensor, Tensor]:
    """(direct image, direct + one-bounce image), each (H, W, 3)."""
    return m.with_bounces(0).render(st.frame, st.gbuffer), m.with_bounces(1).render(st.frame, st.gbuffer)


def _mean(img, mask) -> float:
    return float(img[torch.as_tensor(mask)].mean())


def _default_clusters(n_vertices: int) -> int:
    """Sun 2007 §4.3: "about one cluster per 1000 vertices"."""
    return max(1, round(n_vertices / 1000))


def _ptt_setting(config: dict, name: str) -> Any:
    """A PTT keyword's value in BASE_CONFIG + config, else the constructor's default."""
    import inspect

    from methods.ptt.method import PTT

    cfg = dict(BASE_CONFIG, **config)
    return cfg[name] if name in cfg else inspect.signature(PTT).parameters[name].default


def _resolve_light_res(light_res_1: int, config: dict) -> dict:
    """config + light_res_1 (<= cube_res) and light_res_2 lowered to it if needed (PTT needs
    light_res_2 <= light_res_1 even for one bounce)."""
    cube = _ptt_setting(config, "cube_res")
    if light_res_1 > cube:
        raise ValueError(f"light_res_1 ({light_res_1}) must be <= cube_res ({cube})")
    return dict(config, light_res_1=light_res_1, light_res_2=min(_ptt_setting(config, "light_res_2"), light_res_1))


# -- Fig. 8 -------------------------------------------------------------------------------------


def fig8_lighting_resolution(scene: str = "alcove", size: str = "test", *,
                             light_res: Sequence[int] = FIG8_LIGHT_RES, full: bool = True,
                             spp: int = REF_SPP, config: dict | None = None,
                             out_dir: str | Path | None = None, progress: bool = False):
    """Sun 2007 Fig. 8: the one-bounce image as the PTT's lighting resolution 6×n₁×n₁ grows.

    Args:
        scene, size: `scenes.library.get_scene` arguments.
        light_res: n₁ values (``light_res_1``; powers of two <= cube_res).
        full: also n₁ = cube_res (the "full" one-bounce lighting, no down-sampling) and report every
            row's error against it.
        spp: Mitsuba reference spp; config: extra PTT keyword arguments (over ``BASE_CONFIG``).
        out_dir: if given, write ``fig8.csv``, ``fig8.png`` (errors vs n₁) and ``fig8_images.png``
            (the indirect part per n₁, as the paper's figure).
    Returns:
        DataFrame, one row per n₁: light_res_1, L (= 6 n₁²), rmse_vs_ref (direct + 1 bounce vs
        Mitsuba bounces=1), rmse_indirect_vs_ref (indirect part vs Mitsuba's), rmse_vs_full
        (vs the n₁ = cube_res image; NaN without ``full``), rel_vs_full (rmse_vs_full / mean
        indirect radiance of the full image), indirect_mean, ref_indirect_mean, ref_floor (noise
        floor of the 1-bounce reference), indirect_floor, T1_bytes, precompute_s.
    """
    import pandas as pd
    from tqdm import tqdm

    from references.metrics import rmse

    config = dict(config or {})
    if not light_res:
        raise ValueError("light_res must be non-empty")
    for n in light_res:
        if _check_pos("light_res", n) & (n - 1):
            raise ValueError(f"light_res values must be powers of two, got {n}")
        _resolve_light_res(n, config)  # <= cube_res
    cube = _ptt_setting(config, "cube_res")
    res = sorted(set(light_res) | ({cube} if full else set()))
    st = _setup(scene, size, spp)
    ind_ref = st.ref1.image - st.ref0.image
    out = {}
    for n in tqdm(res, desc="fig8", disable=not progress):
        m, pre = _ptt(st.scene, **_resolve_light_res(n, config))
        i0, i1 = _images(m, st)
        out[n] = (i0, i1, pre, int(m.memory().get("T1", 0)))
        del m
    full_img = out[cube][1] if full else None
    full_ind = (out[cube][1] - out[cube][0]) if full else None
    rows = []
    for n in res:
        i0, i1, pre, nbytes = out[n]
        ind = i1 - i0
        rows.append(dict(
            scene=scene, size=size, light_res_1=n, L=6 * n * n, full=bool(full and n == cube),
            rmse_vs_ref=rmse(i1, st.ref1.image, st.mask),
            rmse_indirect_vs_ref=rmse(ind, ind_ref, st.mask),
            rmse_vs_full=rmse(i1, full_img, st.mask) if full else math.nan,
            rel_vs_full=(rmse(i1, full_img, st.mask) / _mean(full_ind, st.mask)) if full else math.nan,
            indirect_mean=_mean(ind, st.mask), ref_indirect_mean=_mean(ind_ref, st.mask),
            ref_floor=st.ref1.noise_floor, indirect_floor=st.indirect_floor,
            T1_bytes=nbytes, precompute_s=pre))
    df = pd.DataFrame(rows)
    if out_dir is not None:
        od = _outdir(out_dir)
        df.to_csv(od / "fig8.csv", index=False)
        _plot_fig8(df, od / "fig8.png")
        tiles = [(f"6x{n}x{n}" + (" (full)" if full and n == cube else ""), out[n][1] - out[n][0]) for n in res]
        tiles.append(("Mitsuba (1 bounce - direct)", ind_ref))
        _montage(tiles, od / "fig8_images.png", title="Sun 2007 Fig. 8: one-bounce part vs lighting resolution",
                 scale=0.5 / max(_mean(ind_ref, st.mask), 1e-6))
    return df


def _plot_fig8(df, path: Path) -> None:
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(6, 4.5))
    x = df["light_res_1"]
    ax.plot(x, df["rmse_vs_ref"], "o-", label="direct+1 vs Mitsuba 1-bounce")
    ax.plot(x, df["rmse_indirect_vs_ref"], "s-", label="indirect part vs Mitsuba's")
    if df["rmse_vs_full"].notna().any():
        d = df[df["rmse_vs_full"] > 0]
        ax.plot(d["light_res_1"], d["rmse_vs_full"], "^-", label="vs full lighting (n1 = cube_res)")
    ax.axhline(df["ref_floor"].iloc[0], color="gray", ls=":", label="1-bounce reference noise floor")
    ax.axhline(df["indirect_floor"].iloc[0], color="gray", ls="--", label="indirect reference noise floor")
    ax.set_xscale("log", base=2)
    ax.set_yscale("log")
    ax.set_xlabel("one-bounce lighting resolution n1 (6 x n1 x n1)")
    ax.set_ylabel("RMSE")
    ax.set_title(f"Sun 2007 Fig. 8 — {df['scene'].iloc[0]}/{df['size'].iloc[0]}")
    ax.legend(fontsize=7)
    _save(fig, path, plt)


# -- Figs. 9 and 10 -------------------------------------------------------------------------------


def _dense_T1(m) -> Tensor:
    """The dense one-bounce PTT of a precomputed PTT, flattened to (V, R·P·S, L)."""
    T1 = getattr(m, "T1", None)
    if T1 is None or T1.ndim != 5:
        raise ValueError("the PTT has no dense (V, R, P, S, L) T1 (precompute with bounces >= 1, no compress)")
    V, R, P, S, L = T1.shape
    return T1.reshape(V, R * P * S, L)


def fig9_tensor_error(scene: str = "alcove", size: str = "test", *, light_res_1: int = 8,
                      eigenvectors: Sequence[int | None] = FIG9_EIGENVECTORS,
                      light_dims: Sequence[int | None] = FIG9_LIGHT_DIMS, clusters: int | None = None,
                      images: bool = False, spp: int = REF_SPP, config: dict | None = None,
                      out_dir: str | Path | None = None, progress: bool = False):
    """Sun 2007 Fig. 9: clustered tensor approximation error of T¹ over eigenvectors × lighting
    dimension (``methods.ptt.compress``; None = full rank).

    The tensor error ``rel_sq_err`` = ‖T¹ − T̂¹‖²/‖T¹‖² (`compress.relative_error`) is computed from
    one dense precompute; with ``images`` every cell is also rendered by a ``PTT(compress=...)``
    (one precompute each) and scored against the dense image and the Mitsuba 1-bounce reference.
    With one cluster the truncations are nested, so the tensor error cannot grow with either rank;
    with several, CPCA's basis size is ``eigenvectors`` and the clusters change along that axis.

    Args:
        light_res_1: n₁ of T¹ (L = 6 n₁²); clusters: CPCA clusters (default: one per 1000
            vertices, Sun §4.3); the rest as `fig8_lighting_resolution`.
    Returns:
        DataFrame, one row per (eigenvectors, light_dim): clusters, eigenvectors, light_dim (the
        requested value; full rank = n_vertices / L), label, full_rank, rel_sq_err, bytes
        (compressed T¹) and dense_bytes; with images also rmse_vs_dense, rmse_vs_ref,
        rmse_dense_vs_ref.
    """
    import pandas as pd
    from tqdm import tqdm

    from methods.ptt.compress import compress_ptt, relative_error
    from references.metrics import rmse

    config = dict(config or {})
    st = _setup(scene, size, spp) if images else None
    sc = st.scene if st else _scene(scene, size)
    dense, _ = _ptt(sc, **_resolve_light_res(light_res_1, config))
    T = _dense_T1(dense)
    V, D, L = T.shape
    k = _default_clusters(V) if clusters is None else _check_pos("clusters", clusters)
    seed = dense.config["seed"]
    dense_img = dense.render(st.frame, st.gbuffer) if images else None
    grid = _one_cluster_error_grid(T, seed) if k == 1 else None
    rows = []
    cells = [(e, m) for e in eigenvectors for m in light_dims]
    for e, m in tqdm(cells, desc="fig9", disable=not progress):
        ev, lm = _rank(e, V, "eigenvectors"), _rank(m, L, "light_dim")
        if grid is not None:
            err = float(grid[min(ev, V) - 1, min(lm, L) - 1])
            nbytes = _tucker2_bytes(V, D, L, min(ev, V), min(lm, L))
        else:
            ct = compress_ptt(T, clusters=k, eigenvectors=ev, light_dim=lm, seed=seed)
            err = relative_error(T, ct)
            nbytes = sum(t.numel() * t.element_size() for t in ct.tensors())
        row = dict(scene=scene, size=size, light_res_1=light_res_1, L=L, vertices=V, clusters=k,
                   eigenvectors=ev, light_dim=lm, label=_label(e, m), full_rank=(e is None and m is None),
                   rel_sq_err=err, bytes=nbytes, dense_bytes=T.numel() * T.element_size())
        if images:
            mc, _ = _ptt(st.scene, **_resolve_light_res(light_res_1, config),
                         compress=dict(clusters=k, eigenvectors=ev, light_dim=lm))
            img = mc.render(st.frame, st.gbuffer)
            row.update(rmse_vs_dense=rmse(img, dense_img, st.mask), rmse_vs_ref=rmse(img, st.ref1.image, st.mask),
                       rmse_dense_vs_ref=rmse(dense_img, st.ref1.image, st.mask))
        rows.append(row)
    df = pd.DataFrame(rows)
    if out_dir is not None:
        od = _outdir(out_dir)
        df.to_csv(od / "fig9.csv", index=False)
        _plot_fig9(df, od / "fig9.png")
    return df


def _one_cluster_error_grid(T: Tensor, seed: int) -> Tensor:
    """rel_sq_err of the one-cluster Tucker-2 model for every (e, m) from ONE full-rank
    `compress.compress_ptt` (float64).

    The truncated factors of ranks (e, m) are the leading columns of the full-rank ones (the same
    eigendecompositions), and for orthonormal factors ‖X − X̂‖² = ‖X‖² − ‖G[:e, :, :m]‖²
    (Pythagoras, as `brdf_tensor.hosvd_error_grid`), so the whole Fig. 9 grid is a 2-D cumulative
    sum of the squared core (checked against per-cell `compress_ptt` in the tests).

    Args:
        T: (V, D, L). Returns: (V, L) float64, entry [e − 1, m − 1].
    """
    from methods.ptt.compress import compress_ptt

    V, D, L = T.shape
    X = T.double()
    ct = compress_ptt(X, clusters=1, eigenvectors=V, light_dim=L, seed=seed)
    G = ct.G[0]                                   # (V, D, L) core, columns by decreasing energy
    kept = G.square().sum(1).cumsum(0).cumsum(1)  # ‖G[:e, :, :m]‖²
    total = X.square().sum()
    return ((total - kept).clamp_min(0) / total.clamp_min(1e-300))


def _tucker2_bytes(V: int, D: int, L: int, e: int, m: int, itemsize: int = 4) -> int:
    """Stored size of a one-cluster `ClusteredTensor` (ids int64, verts int64, A, G, B float32)."""
    return 8 * V + 8 * V + itemsize * (V * e + e * D * m + L * m)


def _scene(name: str, size: str):
    from scenes.library import get_scene

    return get_scene(name, size)


def _rank(v: int | None, full: int, name: str) -> int:
    return full if v is None else _check_pos(name, v)


def _label(e: int | None, m: int | None) -> str:
    return f"{'full' if e is None else e}/{'full' if m is None else m}"


def _plot_fig9(df, path: Path) -> None:
    plt = _pyplot()
    cols = ["rel_sq_err"] + (["rmse_vs_dense"] if "rmse_vs_dense" in df else [])
    fig, axes = plt.subplots(1, len(cols), figsize=(6 * len(cols), 4.5), squeeze=False)
    for ax, col in zip(axes[0], cols):
        for j, (e, g) in enumerate(df.groupby("eigenvectors")):
            g = g.sort_values("light_dim")
            y = g[col].clip(lower=PLOT_FLOOR)  # full rank is ~1e-15: keep the scale readable
            full = " (full)" if e == g["vertices"].iloc[0] else ""
            ax.plot(g["light_dim"], y, "o-", color=f"C{j % 10}", label=f"{e} eigenvectors{full}")
        ax.set_xscale("log", base=2)
        ax.set_yscale("log")
        ax.set_ylim(bottom=PLOT_FLOOR / 2)
        ax.set_xlabel(f"lighting dimension (of L = {df['L'].iloc[0]})")
        ax.set_ylabel({"rel_sq_err": "||T1 - T1^||^2 / ||T1||^2", "rmse_vs_dense": "image RMSE vs dense T1"}[col])
        ax.legend(fontsize=7)
    fig.suptitle(f"Sun 2007 Fig. 9 — {df['scene'].iloc[0]}/{df['size'].iloc[0]}, "
                 f"{df['clusters'].iloc[0]} cluster(s), 6x{df['light_res_1'].iloc[0]}^2 lighting")
    _save(fig, path, plt)


def fig10_compression_images(scene: str = "alcove", size: str = "test", *, light_res_1: int = 8,
                             combos: Sequence[tuple[int | None, int | None]] = FIG10_COMBOS,
                             clusters: int | None = None, spp: int = REF_SPP, config: dict | None = None,
                             out_dir: str | Path | None = None, progress: bool = False):
    """Sun 2007 Fig. 10: renders with CTA compression levels (eigenvectors / lighting dimension),
    each a ``PTT(compress=dict(clusters, eigenvectors, light_dim))`` precompute, scored against the
    dense-T¹ image and the Mitsuba 1-bounce reference. (None, None) = full rank (must equal the
    dense image: "ground truth" of the paper's figure).

    Returns:
        DataFrame, one row per combo plus one for the dense PTT (label "dense"): label,
        eigenvectors, light_dim (None → the full rank used), clusters, rmse_vs_dense,
        rel_vs_dense (/ mean indirect radiance of the dense image), rmse_vs_ref, bytes
        (``memory()`` of the compressed or dense T¹), precompute_s. With ``out_dir``:
        ``fig10.csv``, ``fig10.png`` (errors per combo) and ``fig10_images.png`` (the renders).
    """
    import pandas as pd
    from tqdm import tqdm

    from references.metrics import rmse

    config = dict(config or {})
    if not combos:
        raise ValueError("combos must be non-empty")
    st = _setup(scene, size, spp)
    lcfg = _resolve_light_res(light_res_1, config)
    dense, pre = _ptt(st.scene, **lcfg)
    V = int(dense.V.shape[0])
    L = 6 * light_res_1 * light_res_1
    k = _default_clusters(V) if clusters is None else _check_pos("clusters", clusters)
    d0, d1 = _images(dense, st)
    ind_mean = _mean(d1 - d0, st.mask)
    rows = [dict(scene=scene, size=size, label="dense", eigenvectors=None, light_dim=None, clusters=0,
                 rmse_vs_dense=0.0, rel_vs_dense=0.0, rmse_vs_ref=rmse(d1, st.ref1.image, st.mask),
                 bytes=int(dense.memory().get("T1", 0)), precompute_s=pre)]
    tiles = []
    for e, m in tqdm(list(combos), desc="fig10", disable=not progress):
        ev, lm = _rank(e, V, "eigenvectors"), _rank(m, L, "light_dim")
        mc, pre = _ptt(st.scene, **lcfg, compress=dict(clusters=k, eigenvectors=ev, light_dim=lm))
        img = mc.render(st.frame, st.gbuffer)
        r = rmse(img, d1, st.mask)
        rows.append(dict(scene=scene, size=size, label=_label(e, m), eigenvectors=ev, light_dim=lm, clusters=k,
                         rmse_vs_dense=r, rel_vs_dense=r / ind_mean, rmse_vs_ref=rmse(img, st.ref1.image, st.mask),
                         bytes=int(mc.memory().get("T1_compressed", 0)), precompute_s=pre))
        tiles.append((f"{_label(e, m)}  rmse {r:.2g}", img))
    df = pd.DataFrame(rows)
    if out_dir is not None:
        od = _outdir(out_dir)
        df.to_csv(od / "fig10.csv", index=False)
        _plot_fig10(df, od / "fig10.png")
        tiles += [("dense T1", d1), ("Mitsuba 1 bounce", st.ref1.image)]
        _montage(tiles, od / "fig10_images.png", title="Sun 2007 Fig. 10: eigenvectors / lighting dimension")
    return df


def _plot_fig10(df, path: Path) -> None:
    plt = _pyplot()
    d = df[df["label"] != "dense"]
    fig, ax = plt.subplots(figsize=(7, 4.5))
    x = range(len(d))
    ax.bar([i - 0.2 for i in x], d["rmse_vs_dense"].clip(lower=1e-12), 0.4, label="vs dense T1 image")
    ax.bar([i + 0.2 for i in x], d["rmse_vs_ref"], 0.4, label="vs Mitsuba 1-bounce")
    ax.axhline(float(df.loc[df["label"] == "dense", "rmse_vs_ref"].iloc[0]), color="k", ls=":",
               label="dense T1 vs Mitsuba")
    ax.set_xticks(list(x), list(d["label"]), rotation=30)
    ax.set_yscale("log")
    ax.set_xlabel("eigenvectors / lighting dimension")
    ax.set_ylabel("RMSE")
    ax.set_title(f"Sun 2007 Fig. 10 — {df['scene'].iloc[0]}/{df['size'].iloc[0]}")
    ax.legend(fontsize=7)
    _save(fig, path, plt)


# -- terms vs exponent (reports.studies contributor) ---------------------------------------------


@lru_cache(maxsize=8)
def _grid(n: int) -> DiskGrid:
    return DiskGrid(n)


@lru_cache(maxsize=64)
def _error_curve(exponent: float, separated: bool, grid_n: int, degrees: tuple[float, ...]) -> tuple[float, ...]:
    from scenes.materials import BlinnPhong

    g = _grid(grid_n)
    # Sun 2007 §3.2: F[h, ωo, ωi] = f_h(ωi, ωo), here N_h = 1, specular only, no cosine
    F = BlinnPhong(kd=0.0, ks=1.0, s=float(exponent)).eval(g.dirs[None, :, :], g.dirs[:, None, :])[..., 0][None]
    norm2 = float(F.square().sum())
    X = separate_tensor(F, g, degrees=degrees)[0] if separated else F  # §4.1: F = F_s + F_r
    # With N_h = 1 the truncated HOSVD of rank (1, b, b) projects the (ωo, ωi) matrix onto its own
    # leading b left and right singular vectors: the rank-b truncated SVD (Eckart–Young), so
    # ‖X − X̂‖² = Σ_{j>b} σ_j² for every b from one `svdvals` (equal to
    # `brdf_tensor.hosvd_error_grid(X, [1], [b])`, checked in the tests; that loop is 10× slower).
    sv2 = torch.linalg.svdvals(X[0]).square().flip(0)
    tail = torch.cumsum(sv2, 0).flip(0)  # tail[j] = Σ_{i>=j} σ_i²
    errs = torch.cat([tail[1:], tail.new_zeros(1)])  # error at rank b = tail[b]
    return tuple(float(e) / norm2 for e in errs)


def tensor_error_curve(exponent: float, *, separated: bool = False, grid_n: int = TERMS_GRID_N,
                       degrees: Sequence[float] = LOBE_DEGREES) -> Tensor:
    """‖F − F̂‖²/‖F‖² of the rank-(1, n_ω, n_ω) Tucker model of one Blinn–Phong BRDF tensor, for
    n_ω = 1..N (module docstring; cached per exponent).

    Args:
        exponent: shininess s > 0; separated: lobe separation (Sun §4.1) before the Tucker fit;
        grid_n: `DiskGrid` resolution (N ≈ π grid_n²/4 directions); degrees: lobe sizes.
    Returns:
        (N,) float64 tensor, entry n_ω − 1; non-increasing, 0 at n_ω = N.
    """
    s = float(exponent)
    if not math.isfinite(s) or s <= 0:
        raise ValueError(f"exponent must be finite and > 0, got {exponent!r}")
    if isinstance(grid_n, bool) or not isinstance(grid_n, int) or grid_n < 2:
        raise ValueError(f"grid_n must be an int >= 2, got {grid_n!r}")
    return torch.tensor(_error_curve(s, bool(separated), grid_n, tuple(float(d) for d in degrees)),
                        dtype=torch.float64)


def _terms(exponent: float, target: float, separated: bool, grid_n: int, degrees: Sequence[float]):

    if not 0 < target < 1:
        raise ValueError(f"target must be in (0, 1), got {target!r}")
    curve = tensor_error_curve(exponent, separated=separated, grid_n=grid_n, degrees=degrees)
    n = int(torch.nonzero(curve <= target)[0, 0]) + 1  # curve[-1] = 0, so always found
    name = "ptt_separated" if separated else "ptt"
    lobes = f"; +{len(degrees)} separated lobes ({'/'.join(f'{d:g}' for d in degrees)} deg) not counted" if separated else ""
    return TermsRecord(name, float(exponent), float(target), n, TERMS_TARGET_KIND.replace(
        f"DiskGrid {TERMS_GRID_N}", f"DiskGrid {grid_n}"),
        f"n_wi = n_wo = {n}, n_h = 1, N = {curve.numel()} directions, rel_sq_err {float(curve[n - 1]):.3g} "
        f"(rank 1: {float(curve[0]):.3g}){lobes}")


def terms_needed(exponent: float, target: float = TERMS_TARGET, *, grid_n: int = TERMS_GRID_N):
    """`reports.studies` contributor "ptt": smallest n_ωi (= n_ωo, n_h = 1) whose Tucker model of
    the Blinn–Phong(s = exponent) BRDF tensor, WITHOUT lobe separation, has ‖F − F̂‖²/‖F‖² <=
    target → ``reports.studies.TermsRecord``."""
    return _terms(exponent, target, False, grid_n, LOBE_DEGREES)


def terms_needed_separated(exponent: float, target: float = TERMS_TARGET, *, grid_n: int = TERMS_GRID_N):
    """Contributor "ptt_separated": as `terms_needed`, WITH Sun §4.1 lobe separation (F̂ = F_s +
    Tucker(F_r), error against the unseparated F; the four lobes are not counted as terms)."""
    return _terms(exponent, target, True, grid_n, LOBE_DEGREES)


def terms_study(exponents: Sequence[float] = TERMS_EXPONENTS, *, targets: Sequence[float] = (0.05, TERMS_TARGET, 0.001),
                grid_n: int = TERMS_GRID_N, out_dir: str | Path | None = None, progress: bool = False):
    """PTT's terms-vs-exponent rows for several targets, with and without lobe separation.

    Returns:
        DataFrame: exponent, target, separated, n_wi (terms), rel_sq_err at n_wi, rank1_err,
        core_terms (n_ωo·n_ωi, the core D's size for n_h = 1). With ``out_dir``:
        ``ptt_terms.csv`` and ``ptt_terms.png``.
    """
    import pandas as pd
    from tqdm import tqdm

    rows = []
    for s in tqdm(list(exponents), desc="ptt terms", disable=not progress):
        for sep in (False, True):
            curve = tensor_error_curve(s, separated=sep, grid_n=grid_n)
            for t in targets:
                r = _terms(s, t, sep, grid_n, LOBE_DEGREES)
                rows.append(dict(exponent=float(s), target=float(t), separated=sep, n_wi=r.terms,
                                 rel_sq_err=float(curve[r.terms - 1]), rank1_err=float(curve[0]),
                                 core_terms=r.terms ** 2, grid_n=grid_n, N=curve.numel()))
    df = pd.DataFrame(rows)
    if out_dir is not None:
        od = _outdir(out_dir)
        df.to_csv(od / "ptt_terms.csv", index=False)
        plt = _pyplot()
        fig, ax = plt.subplots(figsize=(6, 4.5))
        for j, t in enumerate(targets):
            for sep, ls in ((False, "o-"), (True, "s--")):
                d = df[(df["target"] == t) & (df["separated"] == sep)]
                ax.plot(d["exponent"], d["n_wi"], ls, color=f"C{j}",
                        label=f"{'separated' if sep else 'no separation'}, rel sq err <= {t:g}")
        ax.set_xscale("log", base=2)
        ax.set_yscale("log")
        ax.set_xlabel("Blinn-Phong shininess s")
        ax.set_ylabel("n_wi (= n_wo, n_h = 1)")
        ax.set_title(f"PTT BRDF tensor terms vs exponent (DiskGrid {grid_n})")
        ax.legend(fontsize=7)
        _save(fig, od / "ptt_terms.png", plt)
    return df


# -- plotting helpers -----------------------------------------------------------------------------


def _outdir(p: str | Path) -> Path:
    out = Path(p)
    out.mkdir(parents=True, exist_ok=True)
    return out


def _montage(tiles: list[tuple[str, Any]], path: Path, *, title: str, scale: float = 1.0) -> None:
    """Images (H, W, 3) linear → sRGB-ish (× scale, clip, ^1/2.2) in a grid of ≤ 4 columns."""
    plt = _pyplot()
    n = len(tiles)
    cols = min(4, n)
    rows = (n + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(3 * cols, 3 * rows), squeeze=False)
    for ax in axes.flat:
        ax.axis("off")
    for ax, (name, img) in zip(axes.flat, tiles):
        a = torch.as_tensor(img).detach().cpu().double().numpy()
        ax.imshow(np.clip(a * scale, 0, 1) ** (1 / 2.2))
        ax.set_title(name, fontsize=8)
    fig.suptitle(title, fontsize=10)
    _save(fig, path, plt)


# -- registered studies (methods.studies) ---------------------------------------------------------

# Fig. 5 / Fig. 6 quick settings: coarse BRDF grids (seconds).
_FIG5_QUICK = {"grid_n": 8, "n_omega": (4, 8)}
_FIG6_QUICK = {"grid_n": 8, "lobe_sets": ((), (0.0,), (0.0, 7.0))}


def _written(od: Path, names) -> list[Path]:
    return [od / n for n in names if (od / n).exists()]


def study_fig5(out_dir, *, quick: bool = False) -> list[Path]:
    """``sun-fig5``: `fig5` for the Cook–Torrance and Blinn–Phong spaces (full: DiskGrid(24),
    minutes each) → fig5_{ct,bp}.csv and fig5_{ct,bp}_{nosep,sep}.png."""
    od = _outdir(out_dir)
    for kind in ("ct", "bp"):
        fig5(od, kind, **(_FIG5_QUICK if quick else {"progress": True}))
    return _written(od, [f"fig5_{k}{x}" for k in ("ct", "bp") for x in (".csv", "_nosep.png", "_sep.png")])


def study_fig6(out_dir, *, quick: bool = False) -> list[Path]:
    """``sun-fig6``: `fig6_lobe_study` of the Blinn–Phong space → fig6_bp.csv."""
    od = _outdir(out_dir)
    fig6_lobe_study("bp", **(_FIG6_QUICK if quick else {})).to_csv(od / "fig6_bp.csv", index=False)
    return _written(od, ["fig6_bp.csv"])


def study_fig8(out_dir, *, quick: bool = False) -> list[Path]:
    """``sun-fig8``: `fig8_lighting_resolution` on alcove/test (quick: n₁ = 2, 4, no full image)."""
    od = _outdir(out_dir)
    if quick:
        fig8_lighting_resolution(light_res=(2, 4), full=False, out_dir=od)
    else:
        fig8_lighting_resolution(out_dir=od, progress=True)
    return _written(od, ("fig8.csv", "fig8.png", "fig8_images.png"))


def study_fig9(out_dir, *, quick: bool = False) -> list[Path]:
    """``sun-fig9``: `fig9_tensor_error` on alcove/test (quick: 6×4×4 lighting, a 2 × 2 grid)."""
    od = _outdir(out_dir)
    if quick:
        fig9_tensor_error(light_res_1=4, eigenvectors=(8, None), light_dims=(16, None), out_dir=od)
    else:
        fig9_tensor_error(out_dir=od, progress=True)
    return _written(od, ("fig9.csv", "fig9.png"))


def study_fig10(out_dir, *, quick: bool = False) -> list[Path]:
    """``sun-fig10``: `fig10_compression_images` on alcove/test (quick: 6×4×4 lighting, 2 combos)."""
    od = _outdir(out_dir)
    if quick:
        fig10_compression_images(light_res_1=4, combos=((32, 64), (None, None)), out_dir=od)
    else:
        fig10_compression_images(out_dir=od, progress=True)
    return _written(od, ("fig10.csv", "fig10.png", "fig10_images.png"))


def study_terms(out_dir, *, quick: bool = False) -> list[Path]:
    """``ptt-terms``: `terms_study` (quick: s = 4, 16) → ptt_terms.csv / .png."""
    od = _outdir(out_dir)
    if quick:
        terms_study((4.0, 16.0), out_dir=od)
    else:
        terms_study(out_dir=od, progress=True)
    return _written(od, ("ptt_terms.csv", "ptt_terms.png"))


def run_all(out_dir: str | Path, *, quick: bool = False) -> list[Path]:
    """``ptt-figures``: every study of this module into one folder — Figs. 8, 9, 10, the terms
    table, Fig. 5 (both spaces) and Fig. 6; quick = a few cells each. Returns the files written."""
    files: list[Path] = []
    for run in (study_fig8, study_fig9, study_fig10, study_terms, study_fig5, study_fig6):
        files += run(out_dir, quick=quick)
    return files


# -- registration (methods.studies) ----------------------------------------------------------------
# One curve without and one with Sun §4.1 lobe separation (the study plots one curve per name).
register_terms_contributor("ptt", terms_needed, target=0.01,
                           target_kind="relative squared error of the Blinn-Phong BRDF tensor "
                                       "(1 BRDF, DiskGrid 32, n_wo = n_wi) -> n_wi")
register_terms_contributor("ptt_separated", terms_needed_separated, target=0.01,
                           target_kind="relative squared error of the Blinn-Phong BRDF tensor with Sun §4.1 "
                                       "lobe separation (1 BRDF, DiskGrid 32) -> n_wi")
for _name, _desc, _run in (
        ("sun-fig5", "Fig. 5: BRDF tensor error over n_h x n_wi, with and without lobe separation "
                     "(Cook-Torrance and Blinn-Phong spaces)", study_fig5),
        ("sun-fig6", "Fig. 6: BRDF tensor error per sampled BRDF for 0-4 separated lobes", study_fig6),
        ("sun-fig8", "Fig. 8: one-bounce image vs lighting resolution 6 x n1 x n1 (alcove, Mitsuba)", study_fig8),
        ("sun-fig9", "Fig. 9: clustered tensor approximation error of T1 over eigenvectors x lighting "
                     "dimension", study_fig9),
        ("sun-fig10", "Fig. 10: renders at CTA compression levels vs dense T1 and Mitsuba", study_fig10),
        ("ptt-terms", "PTT BRDF tensor terms n_wi vs Blinn-Phong shininess, with and without lobe "
                      "separation", study_terms),
        ("ptt-figures", "Figs. 5, 6, 8, 9, 10 and the terms table, all into one folder", run_all)):
    register_study(Study(_name, f"Sun 2007 {_desc}", _run, paper="Sun 2007"))


# -- term ladder of the one-yardstick terms-vs-exponent study (reports.studies) ----------------
# n_ωi: the incidence components E_x(k) every vertex carries (eq. 3's k), direct lighting only
# (bounces = 0, the study's references are direct), the image figures' BASE_CONFIG otherwise
# (64 rays, 6×16×16 cube map), lobe separation at the PTT default (the lobes are not counted).
TERM_LADDER = tuple(dict(n_wi=n) for n in (1, 2, 3, 4, 6, 8, 12, 16, 24, 32, 48, 64))
TERM_LADDER_QUICK = (dict(n_wi=1, rays=8, cube_res=4, light_res_1=4, light_res_2=2, brdf_grid=8, brdf_table=12,
                          lobe_fit_samples=1024, lobe_vis_samples=256, lobe_theta=8),
                     dict(n_wi=4, rays=8, cube_res=4, light_res_1=4, light_res_2=2, brdf_grid=8, brdf_table=12,
                          lobe_fit_samples=1024, lobe_vis_samples=256, lobe_theta=8))


def make_for_ladder(config: dict, region: str):
    """A direct-lighting PTT with config["n_wi"] incidence components (other keys: constructor
    settings over ``BASE_CONFIG``); ``region`` unused (one factorization for every region)."""
    from methods.ptt.method import PTT

    return PTT(**{**BASE_CONFIG, "bounces": 0, **config})


register_term_ladder("ptt", TERM_LADDER, make_for_ladder, lambda c: c["n_wi"], quick=TERM_LADDER_QUICK,
                     term_name="n_wi (incidence components per vertex)")
