"""Triple-product row of the terms-vs-exponent study (DESIGN.md "Studies"; Ma 2006 §4.1, Figs. 7–8).

For a Phong lobe (kd = 0, ks = 1, exponent s) this measures how many wavelet coefficients per
function (lighting and BRDF slice, both truncated the same way, visibility = 1) the local-frame
triple product needs so that the shaded value B = Σ C L V ρ̃ (Ma 2006 eq. 7) has a relative RMS
error ≤ target against the untruncated product on the same geodesic grid:

    err(n) = ‖B_n − B_K‖ / ‖B_K‖  over  {lighting in `n_frames` random local frames}
                                       × {ωo at θo = 0°, 30°, 60°} × RGB.

The lighting is the procedural ``sky_sun`` map (height 128). The error is the *truncation* error
only; the grid's own resolution limit (level 4: triangles ≈ 3°, so lobes with s ≳ 400 are under
-resolved) is a separate, fixed error not counted here — say so when plotting.

Registration (reports/studies.py, next to the inout line):
    register_terms_contributor("triple_product", "methods.triple_product.study:terms_needed",
                               target=0.05, target_kind="relative RMS shading error (level 4, sky_sun)")
"""
from __future__ import annotations

import math
from functools import lru_cache

import torch

from methods.core.spherical_haar import Geodesic, triple_integral
from methods.triple_product import brdf_table as bt
from methods.triple_product.lighting import project_lighting
from methods.triple_product.precompute import blend_sparse, truncate
from methods.studies import TermsRecord, register_terms_contributor

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
    from references.gbuffer import make_gbuffer
    from references.metrics import rmse
    from scenes.library import get_scene
    from scenes.sequences import make_sequence

    from methods.triple_product.method import TripleProduct

    scene = get_scene(scene_name, size)
    frame = make_sequence(scene, "V", n_frames=1, seed=0)[0]
    gb = make_gbuffer(scene, frame, 1)
    if reference == "mitsuba":  # direct-lighting path-traced reference of the same frame
        from references.render import render_reference

        reference = render_reference(scene, frame, bounces=0, spp=256, seed=0, spp_side=1).image

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
    import csv
    from pathlib import Path

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


def main(argv: list[str] | None = None) -> list:
    """``python -m methods.triple_product.study --out DIR [--scene sphere_plane] [--size test]
    [--level 3]``: the Figs. 7–8 sweep (n = 5 … 640, adaptive and top-only) against the untruncated
    render and a 256-spp Mitsuba direct reference; writes fig7_8.csv / .png and prints the rows."""
    import argparse

    ap = argparse.ArgumentParser(description=main.__doc__)
    ap.add_argument("--out", required=True)
    ap.add_argument("--scene", default="sphere_plane")
    ap.add_argument("--size", default="test")
    ap.add_argument("--level", type=int, default=3)
    a = ap.parse_args(argv)
    rows = truncation_sweep(a.scene, a.size, reference="mitsuba", level=a.level, progress=False)
    for r in rows:
        print(r)
    return plot_truncation_sweep(rows, a.out)


if __name__ == "__main__":
    main()


# -- registration (methods.studies) ----------------------------------------------------------------
register_terms_contributor("triple_product", terms_needed, target=0.05,
                           target_kind="relative RMS shading error vs all coefficients (level 4, sky_sun, V=1)")
