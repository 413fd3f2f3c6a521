"""The cross-method study ``terms-vs-exponent`` (``run_bench.py study terms-vs-exponent``).

Paper figures and tables live beside their methods (``methods/<m>/study.py``) and register in
``methods.studies``; this module holds only what compares methods: it runs Mahajan 2008's
analysis figures (the terms-vs-exponent question is Mahajan's; the figure functions are in
`methods.inout.study`, also registered alone as ``mahajan-fig3a``, ``mahajan-fig2-5``,
``mahajan-fig7c``) and calls every registered terms contributor
(``methods.studies.register_terms_contributor``) and error-vs-terms function.
The in-out row's K is counted in the BRDF's own norm (Mahajan 2008 Fig. 3A: 99 % of the hemisphere
BRDF-matrix energy, 40 × 40 grid); the renderer chooses its K in the cosine-weighted norm (methods/inout).

terms-vs-exponent outputs (in ``out_dir``):
  ``k_vs_s.csv/png`` (Fig. 3A), ``sv_vs_Fl.csv/png`` (Fig. 2 right / Fig. 5),
  ``ts_k_vs_lstar.csv/png`` (Fig. 7C) — see `methods.inout.study`; ``terms_by_method.csv/png``
  (every registered contributor), ``error_vs_terms.csv`` (only if registered), ``summary.json``.
"""
from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import methods.registry  # noqa: F401  (loads every method's study registrations)
from methods.inout import study as mahajan
from methods.studies import ERROR_VS_TERMS, STUDIES, TERMS_CONTRIBUTORS, Study, register_study, run_study, terms_table  # noqa: F401  (STUDIES, run_study: the CLI's)

# -- the terms-vs-exponent study (Mahajan 2008 + contributors) --------------------------------


@dataclass(frozen=True)
class TermsStudyConfig:
    """Sweep sizes. n: grid per direction (paper 40); n_ts_check: a finer grid for the
    Torrance–Sparrow convergence column (0 = skip); table_exponents: the contributors' exponents."""

    s_values: tuple[float, ...] = mahajan.FULL.s_values
    n: int = mahajan.FULL.n
    sv_s: tuple[float, ...] = mahajan.FULL.sv_s
    sigmas: tuple[float, ...] = mahajan.FULL.sigmas
    n_ts_check: int = mahajan.FULL.n_ts_check
    table_exponents: tuple[float, ...] = (1, 2, 4, 8, 16, 32, 64)


FULL_CONFIG = TermsStudyConfig()
QUICK_CONFIG = TermsStudyConfig(s_values=mahajan.QUICK.s_values, n=mahajan.QUICK.n, sv_s=mahajan.QUICK.sv_s,
                                sigmas=mahajan.QUICK.sigmas, n_ts_check=mahajan.QUICK.n_ts_check,
                                table_exponents=(2,))


def terms_vs_exponent(out_dir: Path, *, quick: bool = False,
                      config: TermsStudyConfig | None = None) -> list[Path]:
    """Mahajan 2008 Fig. 2, 3A, 5, 7C + every method's terms-vs-exponent row (module docstring)."""
    from methods.inout.analysis import ENERGY_FRACTION

    cfg = config or (QUICK_CONFIG if quick else FULL_CONFIG)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    plt = mahajan.pyplot()
    n_ts = 1 + (1 if cfg.n_ts_check else 0)
    total = (2 * len(cfg.s_values) + 2 * len(cfg.sv_s) + n_ts * len(cfg.sigmas)
             + len(TERMS_CONTRIBUTORS) * len(cfg.table_exponents)
             + len(ERROR_VS_TERMS) * len(cfg.s_values))
    bar = mahajan.progress_bar(total, "terms-vs-exponent")
    summary: dict[str, Any] = {"n": cfg.n, "energy_fraction": ENERGY_FRACTION, "quick": quick}

    files, s3a = mahajan.fig3a_k_vs_s(out, s_values=cfg.s_values, n=cfg.n, progress=bar)
    summary.update(s3a)
    files += mahajan.fig2_5_singular_values(out, sv_s=cfg.sv_s, n=cfg.n, progress=bar)
    f7c, s7c = mahajan.fig7c_torrance_sparrow(out, sigmas=cfg.sigmas, n=cfg.n, n_ts_check=cfg.n_ts_check,
                                              progress=bar)
    files += f7c
    summary.update(s7c)

    # Every registered method's terms vs exponent.
    recs = terms_table(list(cfg.table_exponents), progress=bar)
    files.append(mahajan.write_csv(out / "terms_by_method.csv", [asdict(r) for r in recs]))
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
    files.append(mahajan.save_fig(fig, out / "terms_by_method.png", plt))

    # Rendered error vs K (Fig. 3B/C, Fig. 6): only when a renderer registered a function.
    if ERROR_VS_TERMS:
        files += mahajan.error_vs_terms_table(out, dict(ERROR_VS_TERMS), cfg.s_values, progress=bar, plot=False)
        summary["error_vs_terms"] = "written"
    else:
        summary["error_vs_terms"] = "pending: no renderer registered (register_error_vs_terms)"
    bar.close()

    path = out / "summary.json"
    path.write_text(json.dumps(summary, indent=2, default=float))
    files.append(path)
    return files


register_study(Study("terms-vs-exponent",
                     "Terms needed vs Phong exponent (Mahajan 2008 Fig. 2, 3A, 5, 7C + every "
                     "registered method)", terms_vs_exponent))
