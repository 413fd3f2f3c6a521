"""Registries of studies and of terms-vs-exponent rows (no study code lives here).

A *study* is a paper figure or table, or a sweep, that writes CSV tables and PNG plots. Each
method package registers its paper's figures in ``methods/<m>/study.py`` at import;
``methods.registry.load_studies()`` imports them all and ``run_bench.py study NAME`` runs one
(``run_bench.py study --list`` lists them). This module sits beside ``methods/base.py`` so method
packages can register without importing ``reports``.

* ``STUDIES`` — name → ``Study(name, description, run, paper)``; ``run(out_dir: Path, *, quick: bool)
  -> list[Path]`` returns the files it wrote. Add one with ``register_study``; run one with
  ``run_study(name, out_dir, quick=False)``.
* ``register_terms_contributor(method, fn, *, target, target_kind)`` — ``fn(exponent, target) ->
  int | TermsRecord``: the number of basis terms ``method`` needs at Phong exponent ``exponent`` to
  reach ``target`` (its meaning: ``target_kind``). The cross-method study
  ``terms-vs-exponent`` (``reports/studies.py``) calls every contributor.
* ``register_error_vs_terms(method, fn)`` — ``fn(exponent, terms) -> rendered image error``.
* ``register_term_ladder(method, ladder, make, terms_of, ...)`` — the method's own term ladder
  (in-out K, SH/ZH order, wavelet coefficients n, PTT n_ωi, ...) for the one-yardstick study
  ``terms-vs-exponent`` (``reports/studies.py``): it renders ``make(config, region)`` at every
  rung it needs and keeps the smallest rung whose image reaches a fixed relative RMSE against a
  Mitsuba reference. Adding a method = one ``register_term_ladder`` call in its ``study.py``.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

# -- registries -------------------------------------------------------------------------------


@dataclass(frozen=True)
class Study:
    """A named sweep. run(out_dir, *, quick) -> files written (quick: test-sized, seconds)."""

    name: str
    description: str
    run: Callable[..., list[Path]]
    paper: str = ""  # the paper whose figures/tables it reproduces ("" for cross-method sweeps)


STUDIES: dict[str, Study] = {}


def register_study(study: Study, *, replace: bool = False) -> Study:
    """Add ``study`` to ``STUDIES`` (``ValueError`` if the name is taken and not ``replace``)."""
    if not isinstance(study, Study):
        raise ValueError(f"expected a Study, got {type(study)}")
    if study.name in STUDIES and not replace:
        raise ValueError(f"study {study.name!r} is already registered")
    STUDIES[study.name] = study
    return study


def run_study(name: str, out_dir: str | Path, *, quick: bool = False, **options: Any) -> list[Path]:
    """Run the study ``name``, writing into ``out_dir`` (created); returns the files written.
    ``options`` (keyword arguments of that study's ``run``, e.g. terms-vs-exponent's ``jobs``,
    ``scenes``, ``exponents``, ``methods``) are passed only when given; a study that takes none of
    them is a ``ValueError``."""
    import inspect

    if name not in STUDIES:
        raise ValueError(f"unknown study {name!r}; known: {', '.join(sorted(STUDIES))}")
    run = STUDIES[name].run
    if options:
        params = inspect.signature(run).parameters
        bad = sorted(k for k in options if k not in params)
        if bad:
            raise ValueError(f"study {name!r} takes no option(s) {bad}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    return list(run(out, quick=quick, **options))


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
    fn: Callable[[float, float], Any]
    target: float
    target_kind: str


TERMS_CONTRIBUTORS: dict[str, TermsContributor] = {}
ERROR_VS_TERMS: dict[str, Callable[[float, int], float]] = {}


def register_terms_contributor(method_name: str, fn: Callable[[float, float], Any], *,
                               target: float = 0.99, target_kind: str = "energy fraction",
                               replace: bool = False) -> TermsContributor:
    """Register ``fn(exponent, target) -> int | TermsRecord`` as ``method_name``'s row of the
    terms-vs-exponent study; ``target`` is the value the study passes (its meaning: target_kind)."""
    if not method_name:
        raise ValueError("method_name must be non-empty")
    if not callable(fn):
        raise ValueError(f"fn must be callable, got {fn!r}")
    if method_name in TERMS_CONTRIBUTORS and not replace:
        raise ValueError(f"terms contributor {method_name!r} is already registered")
    c = TermsContributor(method_name, fn, float(target), target_kind)
    TERMS_CONTRIBUTORS[method_name] = c
    return c


def register_error_vs_terms(method_name: str, fn: Callable[[float, int], float], *,
                            replace: bool = False) -> None:
    """Register ``fn(exponent, terms) -> rendered error`` (Mahajan 2008 Fig. 3B/C, Fig. 6)."""
    if not callable(fn):
        raise ValueError(f"fn must be callable, got {fn!r}")
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
        fn = c.fn
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


# -- term ladders (the one-yardstick terms-vs-exponent study) ---------------------------------


@dataclass(frozen=True)
class TermLadder:
    """A method's configurations ordered by cost, searched by the ``terms-vs-exponent`` study.

    ladder: configs (dicts of the factory's keys), cheapest first; the study assumes the rendered
        error does not grow along it (it bisects) and records the rung below the one it keeps —
        unless ``scan``.
    scan: True when the rendered error can grow from one rung to the next, so a bisection could
        step over the smallest rung that reaches a target (or call a target unreached that a lower
        rung reaches): the study then evaluates the rungs in order from the lowest candidate and keeps
        the first that reaches it. The SH ladders (ZH, SH PRT) set it: a shadowed render truncated
        at order n misses Σ_{l ≥ n} L_lm T_lm, a sum of signed products rather than an orthogonal
        projection's residual, and on sphere_plane at s = 1 the sphere's error reads SH PRT order
        6 / 8 / 10: 3.0 / 6.4 / 2.4 %, ZH (cos θi) order 6 / 7 / 8: 3.9 / 5.1 / 5.9 % (session 48,
        ``python -m benchmarks.yardstick_split``).
    make(config, region) -> an un-precomputed `methods.base.Method`; ``region`` names the scene
        region whose material the study varies (a factory may spend the config's terms there only).
    terms_of(config) -> int: the method's own term count at that rung (non-decreasing along ladder).
    quick: the (short, cheap) ladder of ``--quick`` runs.
    material_at_render: True if ``precompute`` does not read the varied region's material (it is
        applied at render time from ``frame.materials``): one precompute per config serves every
        exponent.
    term_name: what a term is ("K", "n^2 (SH order n)", ...), for the CSV and the legend.
    """

    method: str
    ladder: tuple[dict, ...]
    make: Callable[[dict, str], Any]
    terms_of: Callable[[dict], int]
    quick: tuple[dict, ...]
    material_at_render: bool = False
    term_name: str = "terms"
    note: str = ""
    scan: bool = False


TERM_LADDERS: dict[str, TermLadder] = {}


def register_term_ladder(method_name: str, ladder: Sequence[Mapping], make: Callable[[dict, str], Any],
                         terms_of: Callable[[dict], int] | None = None, *, quick: Sequence[Mapping] | None = None,
                         material_at_render: bool = False, term_name: str = "terms", note: str = "",
                         replace: bool = False, scan: bool = False) -> TermLadder:
    """Register ``method_name``'s term ladder (`TermLadder`). ``terms_of`` defaults to
    ``config["terms"]``; ``quick`` defaults to the ladder's first two rungs. ``ValueError`` for an
    empty ladder, a non-callable factory, terms that decrease along a ladder, or a taken name."""
    if not method_name:
        raise ValueError("method_name must be non-empty")
    if not callable(make):
        raise ValueError(f"make must be callable, got {make!r}")
    if terms_of is None:
        terms_of = _terms_key
    if not callable(terms_of):
        raise ValueError(f"terms_of must be callable, got {terms_of!r}")
    if method_name in TERM_LADDERS and not replace:
        raise ValueError(f"term ladder {method_name!r} is already registered")
    rungs = _check_ladder("ladder", ladder, terms_of)
    q = _check_ladder("quick", ladder[:2] if quick is None else quick, terms_of)
    lad = TermLadder(method_name, rungs, make, terms_of, q, bool(material_at_render), term_name, note, bool(scan))
    TERM_LADDERS[method_name] = lad
    return lad


def _terms_key(config: dict) -> int:
    return config["terms"]


def _check_ladder(name: str, ladder: Sequence[Mapping], terms_of: Callable[[dict], int]) -> tuple[dict, ...]:
    if isinstance(ladder, (str, bytes)) or not isinstance(ladder, Sequence) or not ladder:
        raise ValueError(f"{name} must be a non-empty sequence of config dicts, got {ladder!r}")
    rungs = []
    for c in ladder:
        if not isinstance(c, Mapping):
            raise ValueError(f"{name}: every rung must be a dict, got {c!r}")
        rungs.append(dict(c))
    terms = [terms_of(c) for c in rungs]
    for t in terms:
        if isinstance(t, bool) or int(t) != t or t < 1:
            raise ValueError(f"{name}: terms_of must return ints >= 1, got {terms}")
    if any(b < a for a, b in zip(terms, terms[1:])):
        raise ValueError(f"{name}: terms must not decrease along the ladder, got {terms}")
    return tuple(rungs)


# -- figure plumbing shared by every study module ---------------------------------------------------


def pyplot():
    """matplotlib.pyplot with the Agg backend (studies write files; no display)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_fig(fig, path: Path, plt) -> Path:
    """Tight layout, 110 dpi PNG at ``path``, figure closed; returns ``path``."""
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
