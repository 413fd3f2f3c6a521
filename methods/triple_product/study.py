"""Ma 2006's figures and tables as studies, and the triple product's row of terms-vs-exponent.

Registered studies (``python run_bench.py study NAME [--quick]``):
  * ``ma-fig7-8`` — Figs. 7–8: image RMSE vs coefficients kept per function n (`truncation_sweep`,
    `plot_truncation_sweep`; fig7_8.csv / .png);
  * ``ma-tables`` — Tables 1–2 / §4.1: storage of the local vs global frame parameterisation at the
    paper's settings (`storage_table`; ma_tables.csv / .txt).

Terms-vs-exponent row (DESIGN.md "Studies"; Ma 2006 §4.1, Figs. 7–8):

For a Phong lobe (kd = 0, ks = 1, exponent s) this measures how many wavelet coefficients per
function (lighting and BRDF slice, both truncated the same way, visibility = 1) the local-frame
triple product needs so that the shaded value B = Σ C L V ρ̃ (Ma 2006 eq. 7) has a relative RMS
error ≤ target against the untruncated product on the same geodesic grid:

    err(n) = ‖B_n − B_K‖ / ‖B_K‖  over  {lighting in `n_frames` random local frames}
                                       × {ωo at θo = 0°, 30°, 60°} × RGB.

The lighting is the procedural ``sky_sun`` map (height 128). The error is the *truncation* error
only; the grid's own resolution limit (level 4: triangles ≈ 3°, so lobes with s ≳ 400 are under
-resolved) is a separate, fixed error not counted here — say so when plotting.
"""
from __future__ import annotations

import csv
import math
from functools import lru_cache
from pathlib import Path

import torch

from methods.core.spherical_haar import Geodesic, triple_integral
from methods.triple_product import brdf_table as bt
from methods.triple_product.lighting import project_lighting
from methods.triple_product.precompute import blend_sparse, truncate
from methods.studies import Study, TermsRecord, register_study, register_term_ladder, register_terms_contributor
from methods.triple_product import storage as st

# n ladder searched by `terms_needed` (the paper's 20 / 80 / 320 are on it).
LADDER = (5, 10, 20, 40, 80, 160, 320, 640, 1280, 2560, 5120, 20480)
WO_THETAS_DEG = (0.0, 30.0, 60.0)


def _random_rotations(n: int, seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    q = torch.randn(n, 4, generator=g, dtype=torch.float64)
    q = q / q.norm(dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    return torch.stack([
        torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
        torch.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
        torch.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1)], -2)


@lru_cache(maxsize=4)
def _lighting(level: int, n_frames: int, seed: int) -> torch.Tensor:
    from scenes.envmap import procedural

    env = procedural("sky_sun", height=128, seed=0)
    return project_lighting(env.radiance, _random_rotations(n_frames, seed), Geodesic(level), supersample=1)


@lru_cache(maxsize=64)
def _brdf(exponent: float, level: int) -> torch.Tensor:
    from scenes.materials import Phong

    th = torch.tensor(WO_THETAS_DEG, dtype=torch.float64) * math.pi / 180
    wo = torch.stack([torch.sin(th), torch.zeros_like(th), torch.cos(th)], -1)

    class _Grid(bt.OutgoingGrid):  # exactly these ωo (no interpolation in the study)
        def directions(self, *, dtype=torch.float64):
            return wo.to(dtype)

    mat = Phong(kd=0.0, ks=1.0, s=float(exponent))
    return bt.brdf_table(mat, Geodesic(level), _Grid(2, 1), supersample=2)  # (3 ωo, 3, K)


def shading_error(exponent: float, n: int | None, *, level: int = 4, selection: str = "adaptive",
                  n_frames: int = 8, seed: int = 0) -> float:
    """Relative RMS error of B with n coefficients per function vs all K (module docstring)."""
    L = _lighting(level, n_frames, seed)           # (Fr, 3, K)
    rho = _brdf(float(exponent), level)            # (O, 3, K)
    K = L.shape[-1]
    Fr, O = L.shape[0], rho.shape[0]
    Vc = torch.zeros(K, dtype=torch.float64)
    Vc[:20] = 1.0                                  # V ≡ 1 (level-0 scaling coefficients)

    def trunc(x):
        idx, val = truncate(x, n, selection, level)
        return blend_sparse(idx, val, torch.arange(x.shape[0])[:, None], torch.ones(x.shape[0], 1), K)

    Lf, Rf = L.double()[:, None], rho.double()[None]
    exact = triple_integral(Lf, Vc, Rf)            # (Fr, O, 3)
    Lt, Rt = trunc(L).double()[:, None], trunc(rho).double()[None]
    approx = triple_integral(Lt, Vc, Rt)
    assert exact.shape == (Fr, O, 3)
    return float((approx - exact).norm() / exact.norm().clamp_min(1e-30))


def terms_needed(exponent: float, target: float = 0.05, *, level: int = 4, selection: str = "adaptive"):
    """Smallest n on `LADDER` (≤ K) with `shading_error` ≤ target → ``reports.studies.TermsRecord``."""

    if not 0 < target < 1:
        raise ValueError(f"target must be in (0, 1), got {target}")
    K = 20 * 4 ** level
    n_found, err = K, 0.0
    for n in [m for m in LADDER if m < K] + [K]:
        err = shading_error(exponent, n, level=level, selection=selection)
        if err <= target:
            n_found = n
            break
    return TermsRecord("triple_product", float(exponent), float(target), int(n_found),
                       target_kind="relative RMS shading error vs all coefficients (sky_sun, V=1)",
                       note=f"level {level} ({K} coeffs), {selection}, error {err:.3g} at n")


def truncation_sweep(scene_name: str = "sphere_plane", size: str = "test", *,
                     ns=(5, 10, 20, 40, 80, 160, 320, 640), selections=("adaptive", "top"),
                     reference=None, **config) -> list[dict]:
    """Ma 2006 Figs. 7–8: image RMSE vs n for each selection, against the untruncated render of the
    same configuration (truncation error only) and, if ``reference`` (H, W, 3) is given (or
    ``"mitsuba"``: a 256-spp direct-lighting reference of the frame), against it.

    Returns rows {"selection", "n", "rmse_vs_all", "rmse_vs_reference"}.
    """
    from references.metrics import rmse
    from references.setup import frame_setup
    from scenes.library import get_scene

    from methods.triple_product.method import TripleProduct

    mitsuba = isinstance(reference, str)
    if mitsuba and reference != "mitsuba":
        raise ValueError(f"reference must be None, 'mitsuba' or an (H, W, 3) image, got {reference!r}")
    scene = get_scene(scene_name, size)
    # with "mitsuba": a 256-spp direct-lighting path-traced reference of the same frame
    su = frame_setup(scene, kind="V", n_frames=1, seed=0, spp_side=1, ref_spp=256 if mitsuba else 0,
                     bounces=(0,), ref_spp_side=1)
    frame, gb = su.frame, su.gbuffer
    if mitsuba:
        reference = su.references[0].image

    def render(**kw):
        m = TripleProduct(**{**config, **kw})
        m.precompute(scene)
        return m.render(frame, gb)

    base = render(n_coeffs=None)
    rows = []
    for sel in selections:
        for n in ns:
            img = render(n_coeffs=n, selection=sel)
            rows.append({"selection": sel, "n": n, "rmse_vs_all": rmse(img, base, gb.coverage),
                         "rmse_vs_reference": None if reference is None else rmse(img, reference, gb.coverage)})
    return rows


def plot_truncation_sweep(rows: list[dict], out_dir) -> list:
    """fig7_8.csv and fig7_8.png (RMSE vs n, log-log, one line per selection and error kind)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    csv_path = out / "fig7_8.csv"
    with open(csv_path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    fig, ax = plt.subplots(figsize=(5.5, 4))
    for sel in dict.fromkeys(r["selection"] for r in rows):
        rs = [r for r in rows if r["selection"] == sel]
        ax.loglog([r["n"] for r in rs], [r["rmse_vs_all"] for r in rs], "o-", label=f"{sel}: vs all coefficients")
        if rs[0]["rmse_vs_reference"] is not None:
            ax.loglog([r["n"] for r in rs], [r["rmse_vs_reference"] for r in rs], "s--", label=f"{sel}: vs Mitsuba")
    ax.set_xlabel("coefficients kept per function n")
    ax.set_ylabel("image RMSE")
    ax.set_title("Ma 2006 Figs. 7-8: truncation")
    ax.legend(fontsize=8)
    fig.tight_layout()
    png = out / "fig7_8.png"
    fig.savefig(png, dpi=110)
    plt.close(fig)
    return [csv_path, png]


def fig7_8(out_dir, *, quick: bool = False) -> list[Path]:
    """Study ``ma-fig7-8``: `truncation_sweep` on sphere_plane/test against the untruncated render
    and a 256-spp Mitsuba direct reference, n = 5 … 640, adaptive and top-only, level 3 (quick:
    level 2, n = 10 / 40 / 160, a coarse lighting grid and BRDF table); fig7_8.csv / .png."""
    if quick:
        rows = truncation_sweep("sphere_plane", "test", ns=(10, 40, 160), reference="mitsuba", level=2,
                                frame_grid=(9, 16, 1), brdf_dirs=(4, 8), progress=False)
    else:
        rows = truncation_sweep("sphere_plane", "test", reference="mitsuba", level=3, progress=False)
    return plot_truncation_sweep(rows, out_dir)


# -- Tables 1–2 (storage, §4.1) ---------------------------------------------------------------------


def storage_table(params: dict[str, st.StorageParams] | None = None) -> list[dict]:
    """Rows (setting, local MiB, global MiB, global "GB" as the paper prints it = MiB/1000,
    global GiB) of `storage.storage_bytes` for the paper's isotropic and anisotropic settings
    (or ``params``)."""
    params = params or {"isotropic": st.PAPER_ISOTROPIC, "anisotropic": st.PAPER_ANISOTROPIC}
    rows = []
    for name, p in params.items():
        b = st.storage_bytes(p)
        rows.append({"setting": name, "local_MiB": b["local"] / st.MIB, "global_MiB": b["global"] / st.MIB,
                     "global_paper_GB": b["global"] / st.MIB / 1000, "global_GiB": b["global"] / 2 ** 30})
    return rows


def format_storage_table(params: dict[str, st.StorageParams] | None = None) -> str:
    """`storage_table` as text, with the paper's numbers for comparison."""
    lines = [f"{'setting':<12} {'local [MiB]':>12} {'global [MiB]':>14} {'global [paper GB]':>18} {'global [GiB]':>13}"]
    for r in storage_table(params):
        lines.append(f"{r['setting']:<12} {r['local_MiB']:>12.1f} {r['global_MiB']:>14.1f} "
                     f"{r['global_paper_GB']:>18.2f} {r['global_GiB']:>13.2f}")
    lines.append("Ma 2006 §4.1: local ≈ 170 MB (isotropic) / 480 MB (anisotropic), global ≈ 82 GB (isotropic);"
                 " visibility excluded, 1 material, 4 B/value.")
    return "\n".join(lines)


def tables(out_dir, *, quick: bool = False) -> list[Path]:
    """Study ``ma-tables``: ma_tables.csv and ma_tables.txt (`storage_table`; instant, quick
    changes nothing)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rows = storage_table()
    csv_path = out / "ma_tables.csv"
    with open(csv_path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    txt = out / "ma_tables.txt"
    txt.write_text(format_storage_table() + "\n")
    return [csv_path, txt]


# -- registration (methods.studies) ----------------------------------------------------------------
register_terms_contributor("triple_product", terms_needed, target=0.05,
                           target_kind="relative RMS shading error vs all coefficients (level 4, sky_sun, V=1)")
register_study(Study("ma-fig7-8", "Ma 2006 Figs. 7-8: image RMSE vs wavelet coefficients kept per function "
                     "(adaptive / top), vs all coefficients and vs Mitsuba", fig7_8, paper="Ma 2006"))
register_study(Study("ma-tables", "Ma 2006 Tables 1-2 / §4.1: local vs global frame storage at the paper's "
                     "settings (170 MB / 480 MB / 82 GB)", tables, paper="Ma 2006"))


# -- term ladder of the one-yardstick terms-vs-exponent study (reports.studies) ----------------
# Coefficients kept per function n (Ma 2006 §3.2, "adaptive") at the default level 3 (K = 1280;
# None = all K, the last rung), every other setting at the method's defaults.
TERM_LADDER_LEVEL = 3
TERM_LADDER = tuple(dict(n_coeffs=n) for n in (5, 10, 20, 40, 80, 160, 320, 640, None))
TERM_LADDER_QUICK = (dict(n_coeffs=10, level=1, frame_grid=(5, 8, 1), brdf_dirs=(4, 8)),
                     dict(n_coeffs=None, level=1, frame_grid=(5, 8, 1), brdf_dirs=(4, 8)))


def _ladder_terms(config: dict) -> int:
    n = config["n_coeffs"]
    return 20 * 4 ** config.get("level", TERM_LADDER_LEVEL) if n is None else int(n)


def make_for_ladder(config: dict, region: str):
    """TripleProduct keeping config["n_coeffs"] coefficients per function (other keys: constructor
    settings); ``region`` unused (one n for every function)."""
    from methods.triple_product.method import TripleProduct

    return TripleProduct(**{"level": TERM_LADDER_LEVEL, "progress": False, **config})


register_term_ladder("triple_product", TERM_LADDER, make_for_ladder, _ladder_terms, quick=TERM_LADDER_QUICK,
                     term_name="n (wavelet coefficients per function)")
