"""Precomputation of Nowrouzezahrai et al. 2008 §3: per-pose SH visibility, multi-lobe ZH fits and
the linear pose → ZH model.

Pipeline (one pure function per step):
1. `training_poses`: f poses — the scene's pose animation (`scenes.sequences.make_sequence(scene,
   "P", f, seed)`, the paper trains on animation frames) or joint angles drawn uniformly inside
   the skeleton's limits.
2. `pose_visibility`: per pose, ray-cast binary visibility V(ω) of every vertex of the POSED mesh
   (`scenes.Scene.geometry(pose)`, embreex via `methods.core.visibility.vertex_visibility`) on a
   shared spherical Fibonacci set given in each vertex's local frame (z = skinned normal, tangent
   from `methods.core.frames.coordinate_system`), projected to order-n SH (§3.1: order 4),
   UNWEIGHTED (§3.2) — and, for the Fig. 3 comparison, the cosine-weighted projection of the same
   rays, SH[V(ω) max(0, cos θ)].
3. `fit_zh_lobes`: c ZH lobes per SH vector (§3.1, eq. 1: v_lm = Λ_l Σ_x k^x_l y_lm(s^x)). For a
   fixed axis the least-squares ZH coefficients are closed form (Sloan et al. 2005 §4):
   k_l = Λ_l Σ_m v_lm y_lm(s), and for c lobes the per-band normal equations are
   Σ_x' P_l(s^x·s^x') k^x'_l = Λ_l Σ_m v_lm y_lm(s^x) (since Λ_l² Σ_m y_lm(a) y_lm(b) = P_l(a·b)),
   solved with a small ridge (band 0 is shared by all lobes and otherwise singular). Axes: greedy
   (lobe x = best axis for the residual of lobes < x, searched on a hemisphere grid, since a lobe
   (k, s) equals (k_l (−1)^l, −s)), then a joint Adam refinement of all axes with the coefficients
   re-solved in closed form at every step.
4. Lobe parameterisation for the linear model (6 scalars per lobe, as in the paper): 4 ZH
   coefficients and the axis in the Lambert azimuthal equal-area chart of the local frame,
   (X, Y) = √(2/(1+z)) (x, y). Axes are canonicalised to z ≥ 0 (flipping (k, s) → ((−1)^l k, −s)),
   so (X, Y) lies in the disk of radius √2. Why not (θ, φ): the typical lobe of a mostly unoccluded
   vertex points along the normal, θ ≈ 0, where φ is undefined and jumps by up to π between poses,
   and φ wraps at ±π — a linear model cannot predict either. The equal-area chart is smooth and
   single-valued everywhere on the upper hemisphere (its only singularity is the antipode −z), and
   the normal maps to (0, 0). (A unit 3-vector would need 3 scalars and a renormalisation.)
5. `fit_linear_model`: A X_d = B_d (§3.1), A = [joint angles | 1] (f × (j+1)), B_d (f × v) the
   d-th lobe scalar of every vertex, least squares (one lstsq for all d: they share A).
"""
from __future__ import annotations

import math
import sys
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from methods.core.frames import coordinate_system
from methods.core.sampling import fibonacci_hemisphere, fibonacci_sphere
from methods.core.sh import sh_eval
from methods.core.threads import torch_threads  # noqa: F401  (re-exported: callers use pc.torch_threads)
from methods.core.visibility import vertex_visibility
from references.visibility import make_visibility
from methods.core.zh import band_norms, expand_bands, legendre, zh_lobes_to_sh

# Ridge added to the per-band c × c normal equations of the lobe coefficients when c ≥ 2 (relative
# to the diagonal P_l(1) = 1): band 0 is identical for every lobe (singular without it; the ridge
# splits it evenly), and near-parallel lobes otherwise get huge cancelling coefficients that a
# linear model cannot predict. Measured on the test creature (24 training / 6 held-out animation
# poses, 2 lobes): ridge 1e-3 / 1e-2 / 5e-2 / 0.2 → held-out error 0.095 / 0.073 / 0.073 / 0.099
# (fit error 0.029 / 0.031 / 0.040 / 0.076).
LOBE_RIDGE = 1e-2
# Weight of the pull of each pose's lobe axes towards the vertex's pose-averaged fit (chart units,
# relative to ‖v‖²; `build_model`). It trades a little fit error for parameters that vary smoothly
# with the pose. Measured on the test creature's vertices (24 training / 6 held-out animation
# poses, 512 rays, 2 lobes): anchor 0 / 0.01 / 0.1 / 1 / 3 / 10 → held-out error 0.092 / 0.088 /
# 0.076 / 0.068 / 0.071 / 0.073 (std 0.114 → 0.070); lobe-fit error 0.041 → 0.056 at 1.
AXIS_ANCHOR = 1.0
# Fraction of the training frames that ease in from the rest pose (`training_poses`). Measured on
# the test creature (32 training poses, 1024 rays, default fit; RMSE vs a 256-spp Mitsuba reference
# over 3 rest-pose V frames / 3 animation frames): rest 0 → 0.372 / 0.104 (rest-pose frames 43 %
# too dark: the walk never comes near the rest pose); the rest pose appended as 1 frame → 0.104 /
# 0.104; rest 0.125 → 0.104 / 0.104; rest 0.25 → 0.104 / 0.103.
REST_FRACTION = 0.25
# Largest radius of the equal-area chart (the whole sphere but −z); predictions are clamped to it.
CHART_RMAX = 2.0


# -- 1. training poses ------------------------------------------------------------------------

def training_poses(scene, n: int, *, source: str = "animation", seed: int = 1234,
                   rest: float = REST_FRACTION) -> Tensor:
    """(n, J) training joint angles: a clip that starts at the rest pose (§3.1 trains on animation
    frames; the model must also hold at the poses it is rendered in).

    The first round(rest · n) frames (at least one when rest > 0) ease linearly from the rest pose
    (all joint angles 0, the pose of every V/VB/VBL frame) into the first frame of the clip; the
    remaining frames are the clip: the scene's pose animation ("animation": its P sequence,
    `scenes.sequences.make_sequence(scene, "P", ·, seed)`, which is the character's own clip when the
    scene has one) or joint angles drawn uniformly inside the skeleton's limits ("uniform").
    Why: an animation cycle need not pass near the rest pose (the creature's walk keeps a leg raised
    throughout), and the linear model then extrapolates there. rest = 0 gives the clip alone.
    """
    if scene.skeleton is None:
        raise ValueError(f"scene {scene.name!r} has no skeleton")
    if not isinstance(n, int) or n < 2:
        raise ValueError(f"number of training poses must be an int >= 2, got {n!r}")
    if isinstance(rest, bool) or not isinstance(rest, (int, float)) or not 0.0 <= rest < 1.0:
        raise ValueError("rest (fraction of training frames easing in from the rest pose) must be in [0, 1), "
                         f"got {rest!r}")
    n_rest = 0 if rest == 0 else min(n - 1, max(1, round(rest * n)))
    m = n - n_rest
    if source == "animation":
        from scenes.sequences import make_sequence

        clip = torch.stack([f.pose for f in make_sequence(scene, "P", m, seed=seed)]).float()
    elif source == "uniform":
        sk = scene.skeleton
        J = sk.num_joints
        lim = sk.limits if sk.limits is not None else torch.tensor([[-0.5, 0.5]] * J)
        g = torch.Generator().manual_seed(int(seed))
        u = torch.rand(m, J, generator=g, dtype=torch.float64)
        lo, hi = lim[:, 0].double(), lim[:, 1].double()
        clip = (lo + (hi - lo) * u).float()
    else:
        raise ValueError(f"pose source must be 'animation' or 'uniform', got {source!r}")
    w = torch.arange(n_rest, dtype=torch.float32)[:, None] / max(n_rest, 1)   # 0 (rest), …, < 1
    return torch.cat([w * clip[:1], clip])


# -- 2. visibility --------------------------------------------------------------------------

def pose_visibility(scene, poses: Tensor, order: int, *, n_dirs: int = 1024, below_horizon: str = "trace",
                    progress: bool | None = None) -> tuple[Tensor, Tensor]:
    """SH visibility of every vertex of the posed scene, in the vertex's local frame (§3.1, §3.2).

    Args:
        scene: an articulated `scenes.scene.Scene`; poses: (f, J).
        order: SH order n; n_dirs: Fibonacci directions per vertex (quadrature weight 4π/n_dirs).
        below_horizon: "trace" (the mesh decides; closed meshes block rays below the tangent
            plane) or "hide" (V = 0 below it) — `methods.core.visibility.vertex_visibility`.
    Returns:
        v (f, N, n²) unweighted SH visibility; vcos (f, N, n²) SH of V(ω)·max(0, cos θ); float32.
    """
    from tqdm.auto import tqdm

    poses = torch.as_tensor(poses, dtype=torch.float32)
    if poses.ndim != 2:
        raise ValueError(f"poses must be (f, J), got {tuple(poses.shape)}")
    dirs, w = fibonacci_sphere(int(n_dirs), dtype=torch.float32)
    Y = sh_eval(dirs, order) * w[:, None]                       # (D, n²) quadrature-weighted basis
    Yc = Y * dirs[:, 2:3].clamp_min(0.0)                        # cosine-weighted (local z = normal)
    if progress is None:
        progress = sys.stderr.isatty()
    vs, vcs = [], []
    for pose in tqdm(poses, disable=not progress, desc="zh_shadow visibility", unit="pose"):
        g = scene.geometry(pose)
        vis = make_visibility(g.V, g.F)
        vb = vertex_visibility(vis, g.V, g.N, dirs, local=True, below_horizon=below_horizon,
                               progress=False).float()          # (N, D)
        vs.append(vb @ Y)
        vcs.append(vb @ Yc)
    return torch.stack(vs), torch.stack(vcs)


# -- 3. ZH lobe fitting ----------------------------------------------------------------------

def _band_dot(v: Tensor, Y: Tensor, order: int) -> Tensor:
    """f_l(s) = Σ_m v_lm y_lm(s) per band: v (N, n²), Y (N, L, n²) → (N, L, n)."""
    prod = v[:, None, :] * Y
    return torch.stack([prod[..., l * l:(l + 1) ** 2].sum(-1) for l in range(order)], -1)


def solve_lobe_coeffs(v: Tensor, axes: Tensor, *, ridge: float = LOBE_RIDGE) -> Tensor:
    """Least-squares ZH coefficients of c lobes with fixed axes (per-band normal equations).

    Args:
        v: (N, n²) SH vectors; axes: (N, c, 3) unit axes.
    Returns:
        k (N, c, n).
    """
    N, K = v.shape
    n = math.isqrt(K)
    c = axes.shape[1]
    Y = sh_eval(axes, n)                                        # (N, c, n²)
    lam = band_norms(n, dtype=v.dtype, device=v.device)
    rhs = _band_dot(v, Y, n) * lam                              # (N, c, n): Λ_l f_l(s^x)
    if c == 1:
        return rhs  # exact least squares: Λ_l² Σ_m y_lm(s)² = 1
    G = legendre((axes[:, :, None, :] * axes[:, None, :, :]).sum(-1).clamp(-1, 1), n)  # (N, c, c, n)
    G = G.permute(0, 3, 1, 2) + ridge * torch.eye(c, dtype=v.dtype, device=v.device)   # (N, n, c, c)
    if c == 2:  # Cramer's rule: much faster than a batched LAPACK call on 2 × 2 systems
        a, b, d = G[..., 0, 0], G[..., 0, 1], G[..., 1, 1]
        r0, r1 = rhs[:, 0], rhs[:, 1]                                   # (N, n)
        det = a * d - b * b
        return torch.stack([(d * r0 - b * r1) / det, (a * r1 - b * r0) / det], 1)
    k = torch.linalg.solve(G, rhs.permute(0, 2, 1).unsqueeze(-1)).squeeze(-1)          # (N, n, c)
    return k.permute(0, 2, 1)


def canonical_lobes(k: Tensor, axes: Tensor) -> tuple[Tensor, Tensor]:
    """Flip lobes with axis z < 0: (k_l, s) → ((−1)^l k_l, −s) (the same function). (N, c, n), (N, c, 3)."""
    n = k.shape[-1]
    sgn = torch.where(axes[..., 2:3] < 0, -torch.ones_like(axes[..., 2:3]), torch.ones_like(axes[..., 2:3]))
    par = (-1.0) ** torch.arange(n, dtype=k.dtype, device=k.device)
    k = torch.where(sgn < 0, k * par, k)
    return k, axes * sgn


def chart_to_axis(xy: Tensor) -> Tensor:
    """Lambert azimuthal equal-area chart (X, Y) (..., 2) → unit axes (..., 3); r clamped to 2."""
    r2 = (xy * xy).sum(-1, keepdim=True)
    scale = torch.where(r2 > CHART_RMAX**2, CHART_RMAX / r2.clamp_min(1e-30).sqrt(), torch.ones_like(r2))
    xy = xy * scale
    r2 = (xy * xy).sum(-1, keepdim=True)
    z = 1.0 - 0.5 * r2
    f = (1.0 - 0.25 * r2).clamp_min(0.0).sqrt()
    return torch.cat([f * xy, z], -1)


def axis_to_chart(a: Tensor) -> Tensor:
    """Unit axes (..., 3) → equal-area chart (X, Y) = √(2/(1+z)) (x, y) (..., 2)."""
    return a[..., :2] * (2.0 / (1.0 + a[..., 2:3]).clamp_min(1e-12)).sqrt()


def lobes_to_params(k: Tensor, axes: Tensor) -> Tensor:
    """(N, c, n), (N, c, 3) → (N, c·(2+n)) linear-model scalars [X, Y, k_0..k_{n−1}] per lobe."""
    k, axes = canonical_lobes(k, axes)
    p = torch.cat([axis_to_chart(axes), k], -1)
    return p.reshape(p.shape[0], -1)


def params_to_lobes(p: Tensor, c: int) -> tuple[Tensor, Tensor]:
    """Inverse of `lobes_to_params`: (..., c·(2+n)) → k (..., c, n), axes (..., c, 3)."""
    p = p.reshape(*p.shape[:-1], c, -1)
    return p[..., 2:], chart_to_axis(p[..., :2])


def lobes_sh(k: Tensor, axes: Tensor) -> Tensor:
    """Eq. 1: SH (N, n²) of c lobes k (N, c, n), axes (N, c, 3)."""
    return zh_lobes_to_sh(k, axes.to(k.dtype))


def fit_zh_lobes(v: Tensor, c: int, *, init: Tensor | None = None, n_candidates: int = 400, iters: int = 60,
                 lr: float = 0.05, ridge: float = LOBE_RIDGE, anchor: float = 0.0, canonical: bool = True,
                 chunk: int = 1 << 15) -> tuple[Tensor, Tensor]:
    """Fit c ZH lobes to each SH vector (§3.1 "fit a set of c ZH lobes", eq. 1).

    Args:
        v: (N, n²) SH vectors; c ≥ 1 lobes.
        init: optional (N, c, 3) starting axes (warm start; skips the greedy search).
        n_candidates: hemisphere grid of the greedy axis search;
        iters, lr: Adam steps / step size of the joint axis refinement (0 = greedy/init only).
        ridge: Tikhonov weight of the per-band coefficient solve (`solve_lobe_coeffs`).
        anchor: with `init`, weight of ‖chart(s) − chart(s_init)‖² · ‖v‖² added to the squared error.
        canonical: flip lobes to z ≥ 0 at the end (`canonical_lobes`).
    Returns:
        k (N, c, n), axes (N, c, 3), dtype of v.
    """
    if v.ndim != 2 or math.isqrt(v.shape[1]) ** 2 != v.shape[1]:
        raise ValueError(f"v must be (N, n²), got {tuple(v.shape)}")
    if not isinstance(c, int) or c < 1:
        raise ValueError(f"number of lobes must be an int >= 1, got {c!r}")
    if init is not None and init.shape != (v.shape[0], c, 3):
        raise ValueError(f"init axes must be ({v.shape[0]}, {c}, 3), got {tuple(init.shape)}")
    ks, axs = [], []
    for a in range(0, v.shape[0], chunk):
        k, ax = _fit_chunk(v[a:a + chunk], c, None if init is None else init[a:a + chunk].to(v),
                           n_candidates, iters, lr, ridge, anchor)
        if canonical:
            k, ax = canonical_lobes(k, ax)
        ks.append(k)
        axs.append(ax)
    return torch.cat(ks), torch.cat(axs)


def _greedy_axes(v: Tensor, c: int, n_candidates: int, ridge: float) -> Tensor:
    N, K = v.shape
    n = math.isqrt(K)
    cand, _ = fibonacci_hemisphere(int(n_candidates), dtype=v.dtype, device=v.device)  # E(s) = E(−s)
    Yc = sh_eval(cand, n)                                                     # (D, n²)
    lam2 = band_norms(n, dtype=v.dtype, device=v.device) ** 2
    res = v.clone()
    axes = []
    for _ in range(c):                          # greedy: best single lobe for the residual
        E = sum(lam2[l] * (res[:, l * l:(l + 1) ** 2] @ Yc[:, l * l:(l + 1) ** 2].T) ** 2 for l in range(n))
        s = cand[E.argmax(1)]                                                 # (N, 3)
        axes.append(s)
        kk = solve_lobe_coeffs(res, s[:, None, :], ridge=ridge)
        res = res - lobes_sh(kk, s[:, None, :])
    return torch.stack(axes, 1)                                               # (N, c, 3)


def _fit_chunk(v: Tensor, c: int, init: Tensor | None, n_candidates: int, iters: int, lr: float,
               ridge: float, anchor: float = 0.0) -> tuple[Tensor, Tensor]:
    axes = _greedy_axes(v, c, n_candidates, ridge) if init is None else init
    if iters > 0:
        xy0 = axis_to_chart(axes).detach()
        w = anchor * (v * v).sum(1, keepdim=True)[:, :, None] if (anchor > 0 and init is not None) else None
        xy = xy0.clone().requires_grad_(True)
        opt = torch.optim.Adam([xy], lr=lr)

        def objective(xy_):
            ax = chart_to_axis(xy_)
            e = ((lobes_sh(solve_lobe_coeffs(v, ax, ridge=ridge), ax) - v) ** 2).sum(1)
            if w is not None:  # keep the axes near the warm start (pose-to-pose smoothness)
                e = e + (w * (xy_ - xy0) ** 2).sum((1, 2))
            return e

        for _ in range(iters):
            opt.zero_grad()
            objective(xy).sum().backward()
            opt.step()
        with torch.no_grad():
            ax_new = chart_to_axis(xy)
            e_new = objective(xy)
            e_old = objective(xy0)
            better = (e_new <= e_old)[:, None, None]   # never worse than the starting axes
            axes = torch.where(better, ax_new, axes)
    return solve_lobe_coeffs(v, axes, ridge=ridge).detach(), axes.detach()


# -- 5. the linear model ---------------------------------------------------------------------

def design_matrix(poses: Tensor) -> Tensor:
    """A = [joint angles | 1] (f, J+1) (§3.1)."""
    poses = torch.as_tensor(poses)
    if poses.ndim == 1:
        poses = poses[None]
    return torch.cat([poses, torch.ones(poses.shape[0], 1, dtype=poses.dtype, device=poses.device)], 1)


POSE_RCOND = 1e-6  # relative singular-value cut-off of the pose least squares; float32 poses carry ~1e-7 round-off


def fit_linear_model(poses: Tensor, B: Tensor) -> Tensor:
    """Least-squares A X = B (§3.1), one model per vertex and dimension.

    Args:
        poses: (f, J) training joint angles; B: (f, N, d) per-pose, per-vertex scalars.
    Returns:
        X (J+1, N, d) float32 (last row: the bias).
    """
    f = B.shape[0]
    A = design_matrix(poses).double()
    if A.shape[0] != f:
        raise ValueError(f"poses ({A.shape[0]}) and B ({f}) disagree on the number of frames")
    # Truncate singular values below POSE_RCOND·σ_max: an animation often drives several joints with
    # the same (or an affinely related) curve, so A is rank-deficient; without truncation gelsd keeps
    # round-off singular values (the creature animation spans 4 of its 10 joint dimensions: cond(A) ~ 1e23) and the model explodes (|X| ~ 1e6) at
    # any pose off the training manifold, e.g. the rest pose of V sequences. Truncated = minimum norm.
    X = torch.linalg.lstsq(A, B.reshape(f, -1).double(), rcond=POSE_RCOND, driver="gelsd").solution
    return X.reshape(A.shape[1], *B.shape[1:]).float()


def synthesize(X: Tensor, pose: Tensor) -> Tensor:
    """Run-time step 1 (§4.3): pose (J,) or (F, J) → (N, d) or (F, N, d) = [pose, 1] · X."""
    pose = torch.as_tensor(pose, dtype=X.dtype, device=X.device)
    a = design_matrix(pose)                                  # (F, J+1)
    out = torch.einsum("fj,jnd->fnd", a, X)
    return out[0] if pose.ndim == 1 else out


# -- the whole precomputation ------------------------------------------------------------------

@dataclass
class ZHModel:
    """Run-time data: X (J+1, N, 6c) linear model of [X, Y, k_0..k_{n−1}] per lobe; order n; c lobes."""

    X: Tensor
    order: int
    lobes: int

    def lobes_at(self, pose: Tensor) -> tuple[Tensor, Tensor]:
        """k (N, c, n), local axes (N, c, 3) of every vertex at pose (J,)."""
        return params_to_lobes(synthesize(self.X, pose), self.lobes)

    def sh_at(self, pose: Tensor) -> Tensor:
        """(N, n²) local-frame SH visibility at pose (eq. 1)."""
        k, ax = self.lobes_at(pose)
        return lobes_sh(k, ax)

    @property
    def nbytes(self) -> int:
        return self.X.element_size() * self.X.nelement()


def build_model(v_train: Tensor, poses: Tensor, lobes: int, *, warm_start: bool = True,
                anchor: float = AXIS_ANCHOR, **fit_kw) -> tuple[ZHModel, Tensor]:
    """Fit lobes to every (pose, vertex) SH vector and the linear model on their parameters.

    With ``warm_start`` (default) each vertex's lobes are first fitted to its pose-averaged SH
    vector (greedy search + refinement, canonical z ≥ 0), and every pose's fit starts from those
    axes and is refined locally without re-canonicalising: the lobes then keep their identity and
    vary continuously with the pose, which is what a linear model can predict. (Independent
    per-pose fits let lobes swap, flip sign or jump between near-equivalent optima.) ``anchor``
    (`AXIS_ANCHOR`) additionally penalises moving the axes away from the warm start.

    Args:
        v_train: (f, N, n²); poses: (f, J).
    Returns:
        the model and the per-(pose, vertex) lobe-fit SH (f, N, n²) (before the linear model).
    """
    f, N, K = v_train.shape
    if warm_start:
        _, ref = fit_zh_lobes(v_train.mean(0), lobes, **fit_kw)
        init = ref[None].expand(f, N, lobes, 3).reshape(f * N, lobes, 3)
        k, ax = fit_zh_lobes(v_train.reshape(f * N, K), lobes, init=init, canonical=False, anchor=anchor,
                             **fit_kw)
    else:
        k, ax = fit_zh_lobes(v_train.reshape(f * N, K), lobes, **fit_kw)
    fitted = lobes_sh(k, ax).reshape(f, N, K)
    p = torch.cat([axis_to_chart(ax), k], -1).reshape(f, N, -1)
    return ZHModel(fit_linear_model(poses, p), math.isqrt(K), lobes), fitted


def sh_error(pred: Tensor, true: Tensor, norm: float) -> Tensor:
    """Per-(pose, vertex) L2 error on the sphere (Parseval: coefficient L2) divided by `norm`
    (the L2 norm of the unoccluded function, so 1 = "as wrong as the whole signal"). (...)."""
    return (pred - true).norm(dim=-1) / norm


# L2 norms on the sphere of the unoccluded signals: V ≡ 1 → √(4π); V·max(0, cos θ) → √(2π/3).
NORM_V = math.sqrt(4.0 * math.pi)
NORM_VCOS = math.sqrt(2.0 * math.pi / 3.0)
