"""The scenes' specular lobe families on a fixed set of (ωi, ωo) pairs, split into the part that
depends on the directions only (computed once) and the part that depends on the lobe's parameters
(per material): the run time's BRDF navigation (Sun 2007 §3.1: a changed BRDF is re-expressed in
the basis, H(r, p)) evaluates each changed material's unit-weight lobe on the fit grid of
`transport.LobeBasis._fit`, and only its exponent / roughness change between frames
(``scenes.sequences.perturb_material``; the colours enter the fit linearly, outside this module).

Per family (``scenes.materials``; the formulas are that module's, term by term and in its order of
operations, so the values are *bit-identical* to ``material.eval(wi, wo)[..., 0]`` with kd = 0,
ks = 1 — ``tests/methods/ptt/test_lobe_grid.py`` checks ``torch.equal`` for random parameters):

* Phong (Mahajan 2008 eq. 5): (s+1)/(2π) · max(0, R·ωi)^s · [R·ωi > 0]; cached max(0, R·ωi) and the mask;
* Blinn-Phong: (s+2)/(8π) · max(0, n·h)^s · valid; cached max(0, n·h) and valid;
* Cook-Torrance (Cook & Torrance 1982, Beckmann D, Schlick F, G):
  D = exp(−tan²θh/m²)/(π m² cos⁴θh) · [cos θh > 0], F = F0 + (1−F0)(1 − ωo·h)⁵,
  value D · F · (G/(4 cos θi cos θo) · valid); cached −tan²θh, cos²θh, the mask, (1 − ωo·h)⁵ and the
  G term.

Other families (Torrance-Sparrow, Ward, subclasses) fall back to the material's own ``eval``.
Measured (chess bench materials, 1 thread, CPU time, the 25 200 fit pairs in float64, loaded 2-core
machine): the materials' own evaluation 1.8 / 2.6 / 3.2 ms (Phong / Blinn-Phong / Cook-Torrance)
against 0.36 / 0.46 / 0.29 ms here (one pow or exp per pair and a few multiplies).
"""
from __future__ import annotations

import math

import torch
from torch import Tensor

from scenes import materials as _mat

_TINY = _mat._TINY


# The families `GridLobes.project` evaluates from cached direction factors (exact types only).
FAMILIES = {_mat.Phong: "phong", _mat.BlinnPhong: "blinnphong", _mat.CookTorrance: "cooktorrance"}


class GridLobes:
    """Unit-weight specular lobes of the supported families on the pairs (wi[j], wo[j]).

    wi, wo: (n, 3) local unit directions (any float dtype; the values come out in it, like the
    materials' own evaluation on these tensors)."""

    def __init__(self, wi: Tensor, wo: Tensor) -> None:
        wi, wo = torch.broadcast_tensors(wi, wo)
        self.wi, self.wo = wi, wo
        up = (wi[..., 2] > 0) & (wo[..., 2] > 0)  # Material.eval's horizon test
        self.up = None if bool(up.all()) else up
        self._geo: dict[str, tuple[Tensor, ...]] = {}
        self._grp: dict[str, tuple[Tensor, tuple[Tensor, ...]]] = {}  # `_groups`

    def _geometry(self, family: str) -> tuple[Tensor, ...]:
        g = self._geo.get(family)
        if g is not None:
            return g
        wi, wo = self.wi, self.wo
        if family == "phong":  # scenes.materials.phong_lobe / power_cosine_pdf
            cos_t = _mat._dot(_mat.reflect_z(wo), wi)
            g = (cos_t.clamp_min(0.0), cos_t > 0)
        elif family == "blinnphong":  # blinn_phong_lobe
            h, valid = _mat.half_vector(wi, wo)
            g = (h[..., 2].clamp_min(0.0), valid)
        elif family == "cooktorrance":  # cook_torrance_lobe, beckmann_D
            h, valid = _mat.half_vector(wi, wo)
            nh, ni, no = h[..., 2], wi[..., 2], wo[..., 2]
            oh = _mat._dot(wo, h).clamp_min(_TINY)
            G = torch.minimum(torch.ones_like(nh), torch.minimum(2 * nh * no / oh, 2 * nh * ni / oh))
            c = nh.clamp_min(_TINY)
            c2 = c * c
            tan2 = (1.0 - c2).clamp_min(0.0) / c2
            g = (-tan2, c2, nh > 0, (1.0 - oh).clamp_min(0.0) ** 5, G / (4.0 * ni * no).clamp_min(_TINY) * valid)
        else:
            raise KeyError(family)
        self._geo[family] = g
        return g

    def eval(self, lobe: "_mat.Material") -> Tensor:
        """``lobe.eval(wi, wo)[..., 0]`` (n,) of a unit-weight lobe (kd = 0, ks = 1, as
        ``transport._spec_lobe`` makes it), bit-identical (module docstring)."""
        kind = type(lobe)
        if lobe.kd != (0.0, 0.0, 0.0) or lobe.ks_rgb[0] != 1.0:
            return lobe.eval(self.wi, self.wo)[..., 0]
        if kind is _mat.Phong:
            c, pos = self._geometry("phong")
            s = lobe.s
            v = (s + 1.0) / (2.0 * math.pi) * c.pow(s) * pos
        elif kind is _mat.BlinnPhong:
            c, valid = self._geometry("blinnphong")
            s = lobe.s
            v = (s + 2.0) / (8.0 * math.pi) * c.pow(s) * valid
        elif kind is _mat.CookTorrance:
            ntan2, c2, pos, p5, Gv = self._geometry("cooktorrance")
            m, F0 = lobe.m, lobe.F0
            d = torch.exp(ntan2 / (m * m)) / (math.pi * m * m * c2 * c2)
            D = torch.where(pos, d, torch.zeros_like(d))
            F = F0 + (1.0 - F0) * p5
            v = D * F * Gv
        else:
            return lobe.eval(self.wi, self.wo)[..., 0]
        v = 0.0 + v  # Material.eval: kd/π (= 0) + ks (= 1) · lobe
        return v if self.up is None else torch.where(self.up, v, torch.zeros_like(v))

    def project(self, lobe: "_mat.Material", A: Tensor) -> Tensor:
        """A @ ``eval(lobe)`` ((P,) from A (P, n) on the pairs) with the lobe evaluated once per
        distinct value of its direction factor instead of once per pair.

        Each family's lobe depends on the pair only through one cached factor — max(0, R·ωi) (Phong),
        max(0, n·h) (Blinn-Phong), cos²θh (Cook-Torrance: −tan²θh is a function of it) — times a
        mask and, for Cook-Torrance, per-pair factors that enter linearly (G/(4 cos θi cos θo) ·
        valid, and (1 − ωo·h)⁵ through F = F0 + (1 − F0)(1 − ωo·h)⁵). So Σ_j A_j v_j =
        Σ_u (Σ_{j: factor_j = u} A_j w_j) v(u): the columns of A are summed once per distinct factor
        value (`_groups`, built on the first call per family and A), and a changed material costs
        one pow / exp per distinct value (the fit grid's symmetric pairs repeat them: 25 200 pairs,
        2 529 / 3 494 / 3 494 distinct values for Phong / Blinn-Phong / Cook-Torrance) and a (P, n_u)
        product. The values v(u) are ``eval``'s bits (the same operations on the same factor bits);
        the sum is regrouped, so the result equals ``A @ eval(lobe)`` to float64 round-off
        (``tests/methods/ptt/test_lobe_grid.py``). Pairs masked out (value exactly 0) are dropped.
        Other families and weights: ``A @ eval(lobe)``."""
        kind = type(lobe)
        fam = FAMILIES.get(kind)
        if fam is None or lobe.kd != (0.0, 0.0, 0.0) or lobe.ks_rgb[0] != 1.0:
            return A @ self.eval(lobe).to(A.dtype)
        if fam == "cooktorrance":
            return self.project_family(fam, A, lobe.m, lobe.F0)
        return self.project_family(fam, A, lobe.s)

    def project_family(self, fam: str, A: Tensor, *params: float, as_list: bool = False):
        """`project` of the unit-weight lobe of family ``fam`` (``FAMILIES``' names) with the lobe
        parameters ``params`` (s; Cook-Torrance m, F0), without a lobe object: the same operations, so
        the same bits. as_list: the (P,) result as Python floats (the last combination of Cook-Torrance's
        two products in Python's float64 arithmetic: the same roundings as the tensor ops)."""
        g = self._groups(fam, A)
        if as_list:  # one C call (``native_fit``: the same lobe values, the sums to float64 round-off)
            from methods.ptt import native_fit

            out = native_fit.project(fam, g, params)
            if out is not None:
                return out
        if fam == "phong":
            c, Au = g
            s, = params
            v = (s + 1.0) / (2.0 * math.pi) * c.pow(s)
            out = Au @ (0.0 + v)
            return out.tolist() if as_list else out
        if fam == "blinnphong":
            c, Au = g
            s, = params
            v = (s + 2.0) / (8.0 * math.pi) * c.pow(s)
            out = Au @ (0.0 + v)
            return out.tolist() if as_list else out
        ntan2, c2, A1, A2 = g
        m, F0 = params
        D = torch.exp(ntan2 / (m * m)) / (math.pi * m * m * c2 * c2)
        if as_list:
            w = 1.0 - F0
            return [F0 * a + w * b for a, b in zip((A1 @ D).tolist(), (A2 @ D).tolist())]
        return F0 * (A1 @ D) + (1.0 - F0) * (A2 @ D)

    def _groups(self, family: str, A: Tensor) -> tuple[Tensor, ...]:
        """`project`'s distinct factor values of ``family`` and A's columns summed per value (with the
        pairs' masks and linear factors folded in), cached for the last A per family."""
        grp = self.__dict__.setdefault("_grp", {})
        hit = grp.get(family)
        if hit is not None and hit[0] is A:
            return hit[1]
        g = self._geometry(family)
        keep = g[1] if family != "cooktorrance" else g[2]  # the mask: value exactly 0 outside it
        if self.up is not None:
            keep = keep & self.up
        j = torch.nonzero(keep).squeeze(-1)
        key = (g[0] if family != "cooktorrance" else g[1])[j]
        u, inv = torch.unique(key, return_inverse=True)
        At = A[:, j]

        def fold(w: Tensor | None) -> Tensor:
            x = At if w is None else At * w[j].to(A.dtype)[None, :]
            return torch.zeros(A.shape[0], u.numel(), dtype=A.dtype, device=A.device).index_add_(1, inv, x)

        if family == "cooktorrance":
            ntan2, c2, _, p5, Gv = g
            nt = torch.empty_like(u).scatter_(0, inv, ntan2[j])  # a function of cos²θh: equal within a group
            out = (nt, u, fold(Gv), fold(Gv * p5))
        else:
            out = (u, fold(None))
        grp[family] = (A, out)
        return out
