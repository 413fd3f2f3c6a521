"""Studies: parameter sweeps that write CSV tables and PNG plots (``run_bench.py study <name>``).

Pluggable at two levels.

* ``STUDIES`` — name → ``Study(name, description, run)``; ``run(out_dir: Path, *, quick: bool)
  -> list[Path]`` returns the files it wrote. Add one with ``register_study``; run one with
  ``run_study(name, out_dir, quick=False)``.
* The **terms-vs-exponent** study (DESIGN.md: "studies plot how many basis terms each method needs
  as materials get shinier") has two contributor registries so every method adds its own row
  without this module knowing it:
  - ``register_terms_contributor(method, fn, *, target, target_kind)`` — ONE function
    ``terms_needed(exponent: float, target: float) -> int | TermsRecord``: the number of basis
    terms the method needs for a Phong exponent ``exponent`` to reach ``target`` (what the target
    means is the contributor's ``target_kind``, e.g. "energy fraction" or "relative RMSE").
    ``fn`` may be a callable or a lazy ``"module:function"`` string (imported on first use, so
    registering costs nothing). Built in: ``inout`` → ``methods.inout.analysis:terms_needed``
    (Mahajan 2008: K capturing 99 % of the hemisphere BRDF-matrix energy, 40 × 40 grid, in the
    BRDF's own norm — the renderer counts its K in the cosine-weighted norm, methods/inout).
  - ``register_error_vs_terms(method, fn)`` — ``fn(exponent: float, terms: int) -> float``, the
    rendered image error with ``terms`` terms (Mahajan 2008 Fig. 3B/C, Fig. 6). PENDING: it needs
    the in-out renderer; until one is registered the study writes no error-vs-terms table and says
    so in ``summary.json``.

terms-vs-exponent outputs (in ``out_dir``):
  ``k_vs_s.csv/png`` (Fig. 3A: K(99 %) vs Phong s, sphere and hemisphere, the 5s and 2.5s lines,
  fitted slopes in the legend; the sphere column ``K_exact`` is the grid-free limit from the exact
  F_l, showing that the grid does not cap K), ``sv_vs_Fl.csv/png`` (Fig. 2 right / Fig. 5: singular
  values vs exact F_l, 2l+1 per band on the sphere, l+1 on the hemisphere, and eq. 11's
  approximation), ``ts_k_vs_lstar.csv/png`` (Fig. 7C: K(99 %) vs (l*)² for Torrance–Sparrow
  σ ∈ [0.1, 0.4], fitted line and the paper's (l*)²/4), ``terms_by_method.csv/png`` (every
  registered contributor), ``error_vs_terms.csv/png`` (only if registered), ``summary.json``.
"""
from __future__ import annotations

import csv
import importlib
import json
import math
import sys
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np

# -- registries -------------------------------------------------------------------------------


@dataclass(frozen=True)
class Study:
    """A named sweep. run(out_dir, *, quick) -> files written (quick: test-sized, seconds)."""

    name: str
    description: str
    run: Callable[..., list[Path]]


STUDIES: dict[str, Study] = {}


def register_study(study: Study, *, replace: bool = False) -> Study:
    """Add ``study`` to ``STUDIES`` (``ValueError`` if the name is taken and not ``replace``)."""
    if not isinstance(study, Study):
        raise ValueError(f"expected a Study, got {type(study)}")
    if study.name in STUDIES and not replace:
        raise ValueError(f"study {study.name!r} is already registered")
    STUDIES[study.name] = study
    return study


def run_study(name: str, out_dir: str | Path, *, quick: bool = False) -> list[Path]:
    """Run the study ``name``, writing into ``out_dir`` (created); returns the files written."""
    if name not in STUDIES:
        raise ValueError(f"unknown study {name!r}; known: {', '.join(sorted(STUDIES))}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    return list(STUDIES[name].run(out, quick=quick))


@dataclass(frozen=True)
class TermsRecord:
    """One row of the terms-vs-exponent table.

    method: contributor name; exponent: Phong s; target: accuracy target (meaning: target_kind);
    terms: number of basis terms the method needs; note: free text (resolution, caveats).
    """

    method: str
    exponent: float
    target: float
    terms: int
    target_kind: str = ""
    note: str = ""


@dataclass(frozen=True)
class TermsContributor:
    method: str
    fn: Callable[[float, float], Any] | str  # callable or lazy "module:function"
    target: float
    target_kind: str

    def resolve(self) -> Callable[[float, float], Any]:
        return _resolve(self.fn)


TERMS_CONTRIBUTORS: dict[str, TermsContributor] = {}
ERROR_VS_TERMS: dict[str, Callable[[float, int], float] | str] = {}


def _resolve(fn: Callable | str) -> Callable:
    if callable(fn):
        return fn
    if isinstance(fn, str) and ":" in fn:
        mod, attr = fn.split(":", 1)
        return getattr(importlib.import_module(mod), attr)
    raise ValueError(f"expected a callable or 'module:function', got {fn!r}")


def register_terms_contributor(method_name: str, fn: Callable[[float, float], Any] | str, *,
                               target: float = 0.99, target_kind: str = "energy fraction",
                               replace: bool = False) -> TermsContributor:
    """Register ``fn(exponent, target) -> int | TermsRecord`` as ``method_name``'s row of the
    terms-vs-exponent study; ``target`` is the value the study passes (its meaning: target_kind)."""
    if not method_name:
        raise ValueError("method_name must be non-empty")
    if not (callable(fn) or (isinstance(fn, str) and ":" in fn)):
        raise ValueError(f"fn must be callable or 'module:function', got {fn!r}")
    if method_name in TERMS_CONTRIBUTORS and not replace:
        raise ValueError(f"terms contributor {method_name!r} is already registered")
    c = TermsContributor(method_name, fn, float(target), target_kind)
    TERMS_CONTRIBUTORS[method_name] = c
    return c


def register_error_vs_terms(method_name: str, fn: Callable[[float, int], float] | str, *,
                            replace: bool = False) -> None:
    """Register ``fn(exponent, terms) -> rendered error`` (Mahajan 2008 Fig. 3B/C, Fig. 6).

    PENDING for in-out: needs the renderer (``methods/inout``), which is not written yet.
    """
    if not (callable(fn) or (isinstance(fn, str) and ":" in fn)):
        raise ValueError(f"fn must be callable or 'module:function', got {fn!r}")
    if method_name in ERROR_VS_TERMS and not replace:
        raise ValueError(f"error-vs-terms function {method_name!r} is already registered")
    ERROR_VS_TERMS[method_name] = fn


def terms_table(exponents: list[float], methods: list[str] | None = None, *,
                progress: Any = None) -> list[TermsRecord]:
    """Call every (or the named) contributor at every exponent → records (method-major order)."""
    names = sorted(TERMS_CONTRIBUTORS) if methods is None else methods
    rows: list[TermsRecord] = []
    for name in names:
        if name not in TERMS_CONTRIBUTORS:
            raise ValueError(f"unknown terms contributor {name!r}")
        c = TERMS_CONTRIBUTORS[name]
        fn = c.resolve()
        for s in exponents:
            r = fn(float(s), c.target)
            if isinstance(r, TermsRecord):
                rows.append(r)
            else:
                if int(r) != r or r < 0:
                    raise ValueError(f"{name}: terms_needed returned {r!r}, expected an int >= 0")
                rows.append(TermsRecord(name, float(s), c.target, int(r), c.target_kind))
            if progress is not None:
                progress.update(1)
    return rows


# Built-in contributor (lazy: importing reports.studies imports no method).
register_terms_contributor("inout", "methods.inout.analysis:terms_needed", target=0.99,
                           target_kind="energy fraction (Mahajan 2008, hemisphere, 40x40)")
register_error_vs_terms("inout", "methods.inout.study:error_vs_terms")
register_terms_contributor("triple_product", "methods.triple_product.study:terms_needed", target=0.05,
                           target_kind="relative RMS shading error vs all coefficients (level 4, sky_sun, V=1)")
register_terms_contributor("zh_shadow", "methods.zh_shadow.study:terms_needed", target=0.99,
                           target_kind="energy fraction of the Phong lobe in order-n SH (n² terms)")
# PTT: one curve without and one with Sun §4.1 lobe separation (the study plots one curve per name)
register_terms_contributor("ptt", "methods.ptt.study:terms_needed", target=0.01,
                           target_kind="relative squared error of the Blinn-Phong BRDF tensor "
                                       "(1 BRDF, DiskGrid 32, n_wo = n_wi) -> n_wi")
register_terms_contributor("ptt_separated", "methods.ptt.study:terms_needed_separated", target=0.01,
                           target_kind="relative squared error of the Blinn-Phong BRDF tensor with Sun §4.1 "
                                       "lobe separation (1 BRDF, DiskGrid 32) -> n_wi")


# -- helpers ----------------------------------------------------------------------------------


def _write_csv(path: Path, rows: list[dict]) -> Path:
    if not rows:
        raise ValueError(f"no rows for {path}")
    tmp = path.with_suffix(path.suffix + ".tmp")
    with open(tmp, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    tmp.replace(path)
    return path


def _pyplot():
    import matplotlib  # noqa: PLC0415

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415

    return plt


def fit_line(x, y) -> tuple[float, float]:
    """Least-squares line y ≈ a x + b → (a, b)."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    if x.shape != y.shape or x.size < 2:
        raise ValueError(f"need >= 2 matching points, got {x.shape}, {y.shape}")
    a, b = np.polyfit(x, y, 1)
    return float(a), float(b)


def _progress(total: int, desc: str):
    from tqdm import tqdm  # noqa: PLC0415

    return tqdm(total=total, desc=desc, disable=not sys.stderr.isatty())


# -- the terms-vs-exponent study (Mahajan 2008 + contributors) --------------------------------


@dataclass(frozen=True)
class TermsStudyConfig:
    """Sweep sizes. n: grid per direction (paper 40); n_ts_check: a finer grid for the
    Torrance–Sparrow convergence column (0 = skip)."""

    s_values: tuple[float, ...] = (2, 4, 8, 16, 24, 32, 48, 64)
    n: int = 40
    sv_s: tuple[float, ...] = (10, 30)
    sigmas: tuple[float, ...] = (0.1, 0.15, 0.2, 0.25, 0.3, 0.35, 0.4)
    n_ts_check: int = 60
    table_exponents: tuple[float, ...] = (1, 2, 4, 8, 16, 32, 64)


FULL_CONFIG = TermsStudyConfig()
QUICK_CONFIG = TermsStudyConfig(s_values=(2, 4, 8), n=16, sv_s=(8,), sigmas=(0.3, 0.4),
                                n_ts_check=0, table_exponents=(2,))


def _phong_sphere_fn(s: float):
    from methods.inout.analysis import phong_lobe_sphere  # noqa: PLC0415

    return lambda wi, wo: phong_lobe_sphere(wi, wo, s)


def terms_vs_exponent(out_dir: Path, *, quick: bool = False,
                      config: TermsStudyConfig | None = None) -> list[Path]:
    """Mahajan 2008 Fig. 2, 3A, 5, 7C + every method's terms-vs-exponent row (module docstring)."""
    from methods.inout import analysis as A  # noqa: PLC0415
    from scenes.materials import Phong, TorranceSparrow  # noqa: PLC0415

    cfg = config or (QUICK_CONFIG if quick else FULL_CONFIG)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    plt = _pyplot()
    files: list[Path] = []
    n_ts = 1 + (1 if cfg.n_ts_check else 0)
    total = (2 * len(cfg.s_values) + 2 * len(cfg.sv_s) + n_ts * len(cfg.sigmas)
             + len(TERMS_CONTRIBUTORS) * len(cfg.table_exponents)
             + len(ERROR_VS_TERMS) * len(cfg.s_values))
    bar = _progress(total, "terms-vs-exponent")
    summary: dict[str, Any] = {"n": cfg.n, "energy_fraction": A.ENERGY_FRACTION, "quick": quick}

    # Fig. 3A: K(99 %) vs s on the sphere (idealised lobe) and the hemisphere (physical Phong).
    rows = []
    for s in cfg.s_values:
        sv = A.singular_values(A.brdf_matrix(_phong_sphere_fn(s), cfg.n, "sphere"), "sphere")
        k_sph = A.terms_for_energy(sv)
        bar.update(1)
        M = A.brdf_matrix(Phong(kd=0.0, ks=1.0, s=float(s)), cfg.n, "hemisphere")
        k_hem = A.terms_for_energy(A.singular_values(M, "hemisphere"))
        bar.update(1)
        rows.append({"s": s, "n": cfg.n, "K_sphere": k_sph, "K_hemisphere": k_hem,
                     "K_sphere_exact": A.phong_terms_sphere_exact(s), "grid_size": cfg.n**2})
    files.append(_write_csv(out / "k_vs_s.csv", rows))
    s_arr = np.array([r["s"] for r in rows], float)
    ks = np.array([r["K_sphere"] for r in rows], float)
    kh = np.array([r["K_hemisphere"] for r in rows], float)
    a_s, b_s = fit_line(s_arr, ks)
    a_h, b_h = fit_line(s_arr, kh)
    summary["slope_sphere"], summary["slope_hemisphere"] = a_s, a_h
    summary["max_grid_cap_sphere"] = int(max(abs(r["K_sphere"] - r["K_sphere_exact"]) for r in rows))
    fig, ax = plt.subplots(figsize=(6, 4.5))
    ax.plot(s_arr, ks, "o", color="C0", label=f"sphere, SVD {cfg.n}² (fit {a_s:.2f}s{b_s:+.1f})")
    ax.plot(s_arr, [r["K_sphere_exact"] for r in rows], "x", color="C0", alpha=0.6,
            label="sphere, exact F_l (no grid)")
    ax.plot(s_arr, kh, "s", color="C1", label=f"hemisphere, SVD {cfg.n}² (fit {a_h:.2f}s{b_h:+.1f})")
    xs = np.linspace(0, s_arr.max(), 50)
    ax.plot(xs, 5 * xs, "-", color="C0", lw=1, label="K = 5s (paper, sphere)")
    ax.plot(xs, 2.5 * xs, "-", color="C1", lw=1, label="K = 2.5s (paper, hemisphere)")
    ax.set_xlabel("Phong exponent s")
    ax.set_ylabel("K for 99% energy")
    ax.set_title("Mahajan 2008 Fig. 3A")
    ax.legend(fontsize=8)
    files.append(_save(fig, out / "k_vs_s.png", plt))

    # Fig. 2 right / Fig. 5: singular values vs exact F_l.
    rows = []
    fig, axes = plt.subplots(1, 2, figsize=(10, 4), sharey=True)
    for j, s in enumerate(cfg.sv_s):
        for ax, domain in zip(axes, ("sphere", "hemisphere")):
            fn = _phong_sphere_fn(s) if domain == "sphere" else Phong(kd=0.0, ks=1.0, s=float(s))
            sv = A.singular_values(A.brdf_matrix(fn, cfg.n, domain), domain)
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
    files.append(_write_csv(out / "sv_vs_Fl.csv", rows))
    files.append(_save(fig, out / "sv_vs_Fl.png", plt))

    # Fig. 7C: Torrance–Sparrow K(99 %) vs (l*)².
    rows = []
    for sig in cfg.sigmas:
        mat = TorranceSparrow(kd=0.0, ks=1.0, sigma=float(sig))
        ls = A.l_star(A.half_angle_curve(mat))
        K = A.terms_for_energy(A.singular_values(A.brdf_matrix(mat, cfg.n, "hemisphere"), "hemisphere"))
        bar.update(1)
        row = {"sigma": sig, "l_star": ls, "l_star_sq": ls**2, "K_rule": A.k_rule(mat),
               "n": cfg.n, "K": K}
        if cfg.n_ts_check:
            M = A.brdf_matrix(mat, cfg.n_ts_check, "hemisphere")
            row[f"K_n{cfg.n_ts_check}"] = A.terms_for_energy(A.singular_values(M, "hemisphere"))
            bar.update(1)
        rows.append(row)
    files.append(_write_csv(out / "ts_k_vs_lstar.csv", rows))
    x = np.array([r["l_star_sq"] for r in rows])
    y = np.array([r["K"] for r in rows], float)
    fig, ax = plt.subplots(figsize=(6, 4.5))
    if len(rows) >= 2:
        a_t, b_t = fit_line(x, y)
        summary["ts_slope"], summary["ts_intercept"] = a_t, b_t
        xs = np.linspace(0, x.max(), 50)
        ax.plot(xs, a_t * xs + b_t, "-", color="C0", label=f"fit K = {a_t:.3f}(l*)²{b_t:+.1f}")
    ax.plot(x, y, "o", color="C0", label=f"SVD {cfg.n}²")
    if cfg.n_ts_check:
        ax.plot(x, [r[f"K_n{cfg.n_ts_check}"] for r in rows], "^", color="C2",
                label=f"SVD {cfg.n_ts_check}² (convergence)")
    ax.plot(x, x / 4, "--", color="C1", label="K = (l*)²/4 (paper)")
    for r in rows:
        ax.annotate(f"σ={r['sigma']:g}", (r["l_star_sq"], r["K"]), fontsize=7)
    ax.set_xlabel("(l*)²  (half-angle curve, F_l/F_0 = e⁻³)")
    ax.set_ylabel("K for 99% energy (hemisphere)")
    ax.set_title("Mahajan 2008 Fig. 7C: Torrance–Sparrow")
    ax.legend(fontsize=8)
    files.append(_save(fig, out / "ts_k_vs_lstar.png", plt))
    summary["ts"] = rows

    # Every registered method's terms vs exponent.
    recs = terms_table(list(cfg.table_exponents), progress=bar)
    files.append(_write_csv(out / "terms_by_method.csv", [asdict(r) for r in recs]))
    fig, ax = plt.subplots(figsize=(6, 4.5))
    for name in sorted({r.method for r in recs}):
        rr = [r for r in recs if r.method == name]
        ax.plot([r.exponent for r in rr], [r.terms for r in rr], "o-",
                label=f"{name} ({rr[0].target_kind} {rr[0].target:g})")
    ax.set_xscale("log", base=2)
    ax.set_yscale("log")
    ax.set_xlabel("Phong exponent s")
    ax.set_ylabel("terms needed")
    ax.legend(fontsize=7)
    files.append(_save(fig, out / "terms_by_method.png", plt))

    # Rendered error vs K (Fig. 3B/C, Fig. 6): only when a renderer registered a function.
    if ERROR_VS_TERMS:
        rows = []
        for name, fn in sorted(ERROR_VS_TERMS.items()):
            f = _resolve(fn)
            for s in cfg.s_values:
                for K in sorted({1, 4, 16, max(1, round(2.5 * s)), max(1, round(5 * s))}):
                    rows.append({"method": name, "s": s, "K": K, "error": float(f(float(s), K))})
                bar.update(1)
        files.append(_write_csv(out / "error_vs_terms.csv", rows))
        summary["error_vs_terms"] = "written"
    else:
        summary["error_vs_terms"] = "pending: no renderer registered (register_error_vs_terms)"
    bar.close()

    path = out / "summary.json"
    path.write_text(json.dumps(summary, indent=2, default=float))
    files.append(path)
    return files


def _band_of_index(l_max: int, domain: str) -> list[int]:
    """Band l of each entry of ``repeat_bands`` when F_l is decreasing (multiplicity per band)."""
    from methods.inout.analysis import band_multiplicity  # noqa: PLC0415

    out: list[int] = []
    for l in range(l_max + 1):
        out.extend([l] * band_multiplicity(l, domain))
    return out


def _save(fig, path: Path, plt) -> Path:
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


register_study(Study("terms-vs-exponent",
                     "Terms needed vs Phong exponent (Mahajan 2008 Fig. 2, 3A, 5, 7C + every "
                     "registered method)", terms_vs_exponent))


def _ptt_figures(out_dir: Path, *, quick: bool = False) -> list[Path]:
    from methods.ptt.study import run_all  # noqa: PLC0415  (lazy: no method imported at load)

    return run_all(out_dir, quick=quick)


register_study(Study("ptt-figures", "Sun 2007 Figs. 5-6 (BRDF tensor error, lobe separation), Fig. 8 "
                     "(one-bounce lighting resolution), Figs. 9-10 (CPCA eigenvectors / lighting dimension), "
                     "PTT terms vs shininess", _ptt_figures))
