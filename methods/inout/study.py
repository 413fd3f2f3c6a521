"""Mahajan et al. 2008's analysis figures as studies, and the in-out method's rows of the
cross-method terms-vs-exponent study (`reports.studies`).

Registered studies (``python run_bench.py study NAME [--quick]``; the cross-method study
``terms-vs-exponent`` runs the first three into one folder):
  * ``mahajan-fig3a`` — Fig. 3A (`fig3a_k_vs_s`): K(99 %) vs Phong s on the sphere and the
    hemisphere, the 5s and 2.5s lines, fitted slopes in the legend; the sphere column
    ``K_sphere_exact`` is the grid-free limit from the exact F_l (the grid does not cap K).
    k_vs_s.csv / .png.
  * ``mahajan-fig2-5`` — Fig. 2 right / Fig. 5 (`fig2_5_singular_values`): singular values vs
    exact F_l, 2l+1 per band on the sphere, l+1 on the hemisphere, and eq. 11's approximation.
    sv_vs_Fl.csv / .png.
  * ``mahajan-fig7c`` — Fig. 7C (`fig7c_torrance_sparrow`): K(99 %) vs (l*)² for Torrance–Sparrow
    σ ∈ [0.1, 0.4], fitted line and the paper's (l*)²/4. ts_k_vs_lstar.csv / .png.
  * ``mahajan-fig6`` — Fig. 3B/C, Fig. 6 (`error_vs_terms_table` of `error_vs_terms`): rendered
    error of the K-term in-out image vs K. error_vs_terms.csv / .png.

``error_vs_terms(s, K)``: relative RMSE (RMSE / mean reference radiance, on covered pixels) of the
in-out renderer with K terms on ``sphere_plane`` (test size) whose sphere is a Phong lobe of
exponent s, against Mitsuba's direct-lighting reference (256 spp, cached). Fig. 6's claim is that
K = 2.5 s (hemisphere rule) matches the reference while K = 4 or 12 visibly blur.
"""
from __future__ import annotations

import csv
import dataclasses
import math
import sys
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any, Callable

import numpy as np

from methods.inout import analysis as A
from methods.inout.analysis import terms_needed
from methods.studies import (Study, pyplot, register_error_vs_terms, register_study, register_term_ladder,  # noqa: F401
                             register_terms_contributor, save_fig)

# -- output helpers (also used by reports.studies) ---------------------------------------------------


def write_csv(path: Path, rows: list[dict]) -> Path:
    """rows → CSV at ``path`` (header from the first row; written to a temporary file, then renamed)."""
    if not rows:
        raise ValueError(f"no rows for {path}")
    tmp = path.with_suffix(path.suffix + ".tmp")
    with open(tmp, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    tmp.replace(path)
    return path


def progress_bar(total: int, desc: str):
    """A tqdm bar (hidden when stderr is not a terminal)."""
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, disable=not sys.stderr.isatty())


class _NoBar:
    def update(self, n: int = 1) -> None:
        pass


def fit_line(x, y) -> tuple[float, float]:
    """Least-squares line y ≈ a x + b → (a, b)."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    if x.shape != y.shape or x.size < 2:
        raise ValueError(f"need >= 2 matching points, got {x.shape}, {y.shape}")
    a, b = np.polyfit(x, y, 1)
    return float(a), float(b)


# -- sweep sizes --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class MahajanConfig:
    """Sweep sizes of the analysis figures. n: grid per direction (paper 40); s_values: Fig. 3A
    (and Fig. 6) exponents; sv_s: Fig. 2/5 exponents; sigmas: Fig. 7C roughnesses; n_ts_check: a
    finer grid for the Torrance–Sparrow convergence column (0 = skip)."""

    s_values: tuple[float, ...] = (2, 4, 8, 16, 24, 32, 48, 64)
    n: int = 40
    sv_s: tuple[float, ...] = (10, 30)
    sigmas: tuple[float, ...] = (0.1, 0.15, 0.2, 0.25, 0.3, 0.35, 0.4)
    n_ts_check: int = 60


FULL = MahajanConfig()
QUICK = MahajanConfig(s_values=(2, 4, 8), n=16, sv_s=(8,), sigmas=(0.3, 0.4), n_ts_check=0)
# Fig. 6 renders: one Mitsuba reference per exponent and one precompute per (s, K).
FIG6_S = (2, 4, 8, 16, 24, 32, 48, 64)
FIG6_S_QUICK = (4,)


def _phong_sphere_fn(s: float):
    return lambda wi, wo: A.phong_lobe_sphere(wi, wo, s)


def _band_of_index(l_max: int, domain: str) -> list[int]:
    """Band l of each entry of ``repeat_bands`` when F_l is decreasing (multiplicity per band)."""
    out: list[int] = []
    for l in range(l_max + 1):
        out.extend([l] * A.band_multiplicity(l, domain))
    return out


# -- Fig. 3A ----------------------------------------------------------------------------------------


def fig3a_k_vs_s(out_dir, *, s_values=FULL.s_values, n: int = FULL.n, progress=None) -> tuple[list[Path], dict]:
    """Mahajan 2008 Fig. 3A: K(99 %) vs s on the sphere (idealised lobe) and the hemisphere
    (physical Phong). Writes k_vs_s.csv / .png; returns (files, summary) with the fitted slopes
    ``slope_sphere``, ``slope_hemisphere`` and ``max_grid_cap_sphere`` (max |K_sphere − K_exact|)."""
    from scenes.materials import Phong

    out, bar, plt = Path(out_dir), progress or _NoBar(), pyplot()
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for s in s_values:
        sv = A.singular_values(A.brdf_matrix(_phong_sphere_fn(s), n, "sphere"), "sphere")
        k_sph = A.terms_for_energy(sv)
        bar.update(1)
        M = A.brdf_matrix(Phong(kd=0.0, ks=1.0, s=float(s)), n, "hemisphere")
        k_hem = A.terms_for_energy(A.singular_values(M, "hemisphere"))
        bar.update(1)
        rows.append({"s": s, "n": n, "K_sphere": k_sph, "K_hemisphere": k_hem,
                     "K_sphere_exact": A.phong_terms_sphere_exact(s), "grid_size": n**2})
    files = [write_csv(out / "k_vs_s.csv", rows)]
    s_arr = np.array([r["s"] for r in rows], float)
    ks = np.array([r["K_sphere"] for r in rows], float)
    kh = np.array([r["K_hemisphere"] for r in rows], float)
    a_s, b_s = fit_line(s_arr, ks)
    a_h, b_h = fit_line(s_arr, kh)
    summary = {"slope_sphere": a_s, "slope_hemisphere": a_h,
               "max_grid_cap_sphere": int(max(abs(r["K_sphere"] - r["K_sphere_exact"]) for r in rows))}
    fig, ax = plt.subplots(figsize=(6, 4.5))
    ax.plot(s_arr, ks, "o", color="C0", label=f"sphere, SVD {n}² (fit {a_s:.2f}s{b_s:+.1f})")
    ax.plot(s_arr, [r["K_sphere_exact"] for r in rows], "x", color="C0", alpha=0.6,
            label="sphere, exact F_l (no grid)")
    ax.plot(s_arr, kh, "s", color="C1", label=f"hemisphere, SVD {n}² (fit {a_h:.2f}s{b_h:+.1f})")
    xs = np.linspace(0, s_arr.max(), 50)
    ax.plot(xs, 5 * xs, "-", color="C0", lw=1, label="K = 5s (paper, sphere)")
    ax.plot(xs, 2.5 * xs, "-", color="C1", lw=1, label="K = 2.5s (paper, hemisphere)")
    ax.set_xlabel("Phong exponent s")
    ax.set_ylabel("K for 99% energy")
    ax.set_title("Mahajan 2008 Fig. 3A")
    ax.legend(fontsize=8)
    files.append(save_fig(fig, out / "k_vs_s.png", plt))
    return files, summary


# -- Fig. 2 right / Fig. 5 ------------------------------------------------------------------------------


def fig2_5_singular_values(out_dir, *, sv_s=FULL.sv_s, n: int = FULL.n, progress=None) -> list[Path]:
    """Mahajan 2008 Fig. 2 right / Fig. 5: singular values vs exact F_l (sphere: 2l+1 per band;
    hemisphere: l+1) and eq. 11's exp(−l²/2s). Writes sv_vs_Fl.csv / .png."""
    from scenes.materials import Phong

    out, bar, plt = Path(out_dir), progress or _NoBar(), pyplot()
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    fig, axes = plt.subplots(1, 2, figsize=(10, 4), sharey=True)
    for j, s in enumerate(sv_s):
        for ax, domain in zip(axes, ("sphere", "hemisphere")):
            fn = _phong_sphere_fn(s) if domain == "sphere" else Phong(kd=0.0, ks=1.0, s=float(s))
            sv = A.singular_values(A.brdf_matrix(fn, n, domain), domain)
            bar.update(1)
            K = A.terms_for_energy(sv)
            kmax = min(sv.numel(), max(2 * K, 20))
            l_max = int(math.isqrt(kmax)) * 2 + 2
            F = A.phong_F(s, l_max)
            pred = A.repeat_bands(F, domain)[:kmax]
            l_of_k = _band_of_index(l_max, domain)[:kmax]
            for k in range(kmax):
                rows.append({"s": s, "domain": domain, "k": k + 1, "sigma": float(sv[k]),
                             "l": int(l_of_k[k]), "F_l": float(pred[k]),
                             "F_l_approx": math.exp(-l_of_k[k] ** 2 / (2 * s))})
            kk = np.arange(1, kmax + 1)
            ax.plot(kk, sv[:kmax].numpy(), "o", ms=3, color=f"C{j}", label=f"SVD s={s:g}")
            ax.plot(kk, pred.numpy(), "-", color=f"C{j}", label=f"exact F_l, s={s:g}")
            ax.plot(kk, [math.exp(-l**2 / (2 * s)) for l in l_of_k], ":", color=f"C{j}",
                    label=f"exp(-l²/2s), s={s:g}")
            ax.axvline(K, color=f"C{j}", lw=0.5, ls="--")
    axes[0].set_title("sphere: F_l repeated 2l+1 times (Fig. 2)")
    axes[1].set_title("hemisphere: F_l repeated l+1 times (Fig. 5)")
    for ax in axes:
        ax.set_xlabel("index k (sorted)")
        ax.legend(fontsize=7)
    axes[0].set_ylabel("singular value (operator scale)")
    return [write_csv(out / "sv_vs_Fl.csv", rows), save_fig(fig, out / "sv_vs_Fl.png", plt)]


# -- Fig. 7C ------------------------------------------------------------------------------------------


def fig7c_torrance_sparrow(out_dir, *, sigmas=FULL.sigmas, n: int = FULL.n, n_ts_check: int = FULL.n_ts_check,
                           progress=None) -> tuple[list[Path], dict]:
    """Mahajan 2008 Fig. 7C: Torrance–Sparrow K(99 %) vs (l*)². Writes ts_k_vs_lstar.csv / .png;
    returns (files, summary) with ``ts_slope``, ``ts_intercept`` (>= 2 sigmas) and the rows ``ts``."""
    from scenes.materials import TorranceSparrow

    out, bar, plt = Path(out_dir), progress or _NoBar(), pyplot()
    out.mkdir(parents=True, exist_ok=True)
    summary: dict[str, Any] = {}
    rows = []
    for sig in sigmas:
        mat = TorranceSparrow(kd=0.0, ks=1.0, sigma=float(sig))
        ls = A.l_star(A.half_angle_curve(mat))
        K = A.terms_for_energy(A.singular_values(A.brdf_matrix(mat, n, "hemisphere"), "hemisphere"))
        bar.update(1)
        row = {"sigma": sig, "l_star": ls, "l_star_sq": ls**2, "K_rule": A.k_rule(mat), "n": n, "K": K}
        if n_ts_check:
            M = A.brdf_matrix(mat, n_ts_check, "hemisphere")
            row[f"K_n{n_ts_check}"] = A.terms_for_energy(A.singular_values(M, "hemisphere"))
            bar.update(1)
        rows.append(row)
    files = [write_csv(out / "ts_k_vs_lstar.csv", rows)]
    x = np.array([r["l_star_sq"] for r in rows])
    y = np.array([r["K"] for r in rows], float)
    fig, ax = plt.subplots(figsize=(6, 4.5))
    if len(rows) >= 2:
        a_t, b_t = fit_line(x, y)
        summary["ts_slope"], summary["ts_intercept"] = a_t, b_t
        xs = np.linspace(0, x.max(), 50)
        ax.plot(xs, a_t * xs + b_t, "-", color="C0", label=f"fit K = {a_t:.3f}(l*)²{b_t:+.1f}")
    ax.plot(x, y, "o", color="C0", label=f"SVD {n}²")
    if n_ts_check:
        ax.plot(x, [r[f"K_n{n_ts_check}"] for r in rows], "^", color="C2",
                label=f"SVD {n_ts_check}² (convergence)")
    ax.plot(x, x / 4, "--", color="C1", label="K = (l*)²/4 (paper)")
    for r in rows:
        ax.annotate(f"σ={r['sigma']:g}", (r["l_star_sq"], r["K"]), fontsize=7)
    ax.set_xlabel("(l*)²  (half-angle curve, F_l/F_0 = e⁻³)")
    ax.set_ylabel("K for 99% energy (hemisphere)")
    ax.set_title("Mahajan 2008 Fig. 7C: Torrance–Sparrow")
    ax.legend(fontsize=8)
    files.append(save_fig(fig, out / "ts_k_vs_lstar.png", plt))
    summary["ts"] = rows
    return files, summary


# -- Fig. 3B/C, Fig. 6: rendered error vs K -----------------------------------------------------------


def fig6_terms(s: float) -> list[int]:
    """The K values of the error-vs-terms sweep at exponent s: 1, 4, 16, 2.5 s and 5 s (the two rules)."""
    return sorted({1, 4, 16, max(1, round(2.5 * s)), max(1, round(5 * s))})


def error_vs_terms_table(out_dir, fns: dict[str, Callable[[float, int], float]], s_values, *,
                         terms: Callable[[float], list[int]] = fig6_terms, progress=None,
                         plot: bool = True) -> list[Path]:
    """Rendered error ``fn(s, K)`` of every function in ``fns`` (name → fn) at every s and every K
    of ``terms(s)``: error_vs_terms.csv (method, s, K, error) and, with ``plot``, error_vs_terms.png."""
    out, bar = Path(out_dir), progress or _NoBar()
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for name, fn in sorted(fns.items()):
        for s in s_values:
            for K in terms(s):
                rows.append({"method": name, "s": s, "K": K, "error": float(fn(float(s), K))})
            bar.update(1)
    files = [write_csv(out / "error_vs_terms.csv", rows)]
    if plot:
        plt = pyplot()
        fig, ax = plt.subplots(figsize=(6, 4.5))
        for i, key in enumerate(dict.fromkeys((r["method"], r["s"]) for r in rows)):
            rr = [r for r in rows if (r["method"], r["s"]) == key]
            ax.plot([r["K"] for r in rr], [r["error"] for r in rr], "o-", color=f"C{i % 10}",
                    label=f"{key[0]}, s={key[1]:g}")
            ax.axvline(2.5 * key[1], color=f"C{i % 10}", lw=0.5, ls="--")
        ax.set_xscale("log")
        ax.set_xlabel("terms K (dashed: K = 2.5 s)")
        ax.set_ylabel("relative RMSE vs Mitsuba")
        ax.set_title("Mahajan 2008 Fig. 3B/C, Fig. 6: rendered error vs K")
        ax.legend(fontsize=7)
        files.append(save_fig(fig, out / "error_vs_terms.png", plt))
    return files


REF_SPP = 256  # reference samples per pixel (noise floor ≈ 5 % of the RMSE scale at this size)


@lru_cache(maxsize=16)
def _setup(s: float):
    """sphere_plane/test with a Phong-s sphere: (scene, frame, G-buffer, 0-bounce reference, mask)."""
    from references.setup import frame_setup
    from scenes.library import get_scene
    from scenes.materials import Phong
    from scenes.sequences import make_sequence

    scene = get_scene("sphere_plane", "test")
    old = scene.materials["sphere"]
    mats = dict(scene.materials)
    mats["sphere"] = Phong(kd=old.kd, ks=old.ks, s=float(s))
    scene = dataclasses.replace(scene, materials=mats)
    frame = dataclasses.replace(make_sequence(scene, "V", n_frames=1, seed=0)[0], materials=mats)
    su = frame_setup(scene, frames=[frame], spp_side=2, ref_spp=REF_SPP, bounces=(0,), seed=0)
    return scene, frame, su.gbuffer, su.references[0], su.mask(0)


def error_vs_terms(exponent: float, terms: int) -> float:
    """Relative RMSE of the K-term in-out image of a Phong-s sphere (module docstring)."""
    from methods.inout.method import InOut
    from references.metrics import rmse

    scene, frame, gb, ref, mask = _setup(float(exponent))
    m = InOut(terms=int(terms), progress=False)
    m.precompute(scene)
    return rmse(m.render(frame, gb), ref.image, mask) / ref.image[mask].mean().item()


def _study(name: str, description: str, fn):
    register_study(Study(name, f"Mahajan 2008 {description}", fn, paper="Mahajan 2008"))


def _fig3a(out, *, quick: bool):
    c = QUICK if quick else FULL
    return fig3a_k_vs_s(out, s_values=c.s_values, n=c.n)[0]


def _fig2_5(out, *, quick: bool):
    c = QUICK if quick else FULL
    return fig2_5_singular_values(out, sv_s=c.sv_s, n=c.n)


def _fig7c(out, *, quick: bool):
    c = QUICK if quick else FULL
    return fig7c_torrance_sparrow(out, sigmas=c.sigmas, n=c.n, n_ts_check=c.n_ts_check)[0]


def _fig6(out, *, quick: bool):
    if quick:  # s = 4 at K = 4 (blurred) and K = 2.5 s (the hemisphere rule)
        return error_vs_terms_table(out, {"inout": error_vs_terms}, FIG6_S_QUICK,
                                    terms=lambda s: [4, round(2.5 * s)])
    return error_vs_terms_table(out, {"inout": error_vs_terms}, FIG6_S)


# -- registration (methods.studies) ----------------------------------------------------------------
register_terms_contributor("inout", terms_needed, target=0.99,
                           target_kind="energy fraction (Mahajan 2008, hemisphere, 40x40)")
register_error_vs_terms("inout", error_vs_terms)
_study("mahajan-fig3a", "Fig. 3A: terms K(99 %) vs Phong exponent, sphere and hemisphere", _fig3a)
_study("mahajan-fig2-5", "Figs. 2 and 5: singular values vs the exact Phong F_l", _fig2_5)
_study("mahajan-fig7c", "Fig. 7C: Torrance-Sparrow K(99 %) vs (l*)^2", _fig7c)
_study("mahajan-fig6", "Figs. 3B/C and 6: rendered in-out error vs K (Mitsuba references)", _fig6)


# -- term ladder of the one-yardstick terms-vs-exponent study (reports.studies) ----------------
# K on the varied (glossy) region; every other region keeps its rule (Lambert: K = 1); every other
# setting at the method's defaults (brdf_res 24, cube_res 16: the lighting texel, not K, limits
# the sharpest lobes). Ratio between rungs <= 1.5 so the study's step is fine.
TERM_LADDER = tuple(dict(terms=k) for k in (1, 2, 3, 4, 6, 8, 12, 16, 24, 32, 48, 64, 96, 128, 192, 256))
TERM_LADDER_QUICK = (dict(terms=1, brdf_res=8, cube_res=8, n_coeffs=32),
                     dict(terms=4, brdf_res=8, cube_res=8, n_coeffs=32))


def make_for_ladder(config: dict, region: str):
    """InOut with K = config["terms"] on ``region`` (other config keys: constructor settings)."""
    from methods.inout.method import InOut

    cfg = dict(config)
    return InOut(terms={region: int(cfg.pop("terms"))}, progress=False, **cfg)


register_term_ladder("inout", TERM_LADDER, make_for_ladder, quick=TERM_LADDER_QUICK, term_name="K (in-out terms)")
