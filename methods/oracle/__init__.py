"""Oracle: brute-force direct lighting, the convention check of the whole suite.

For every G-buffer sample x with outgoing direction ωo it estimates

    B(x, ωo) = ∫_{S²} L(ω) V(x, ω) f(ω, ωo) max(0, n·ω) dω

with multiple importance sampling (Veach 1997, power heuristic β = 2) of two strategies: the env
map's luminance distribution (``EnvMap.sample``) and the material's lobe (``Material.sample``).
Visibility is traced by ``references.visibility.make_visibility`` (Mitsuba's ``ray_test`` or embreex,
``PRTBENCH_VISIBILITY``). The estimator is the same one
Mitsuba's ``path`` integrator uses for ``max_depth = 2``, so oracle and reference must agree up to
noise; a bias means a convention differs somewhere (env-map orientation, BRDF normalisation,
cosine placement, camera rays, normals). ``tests/methods/test_oracle.py`` proves it on every named
scene and procedural env map.

No precomputation: it handles dynamic lighting, view, BRDFs and geometry (a posed mesh per frame).

Two paths compute the same estimate from the same random numbers (issue 14): `Oracle.render_reference`,
the eager estimator (`Oracle._shade` per region and batch of samples), is the test oracle;
`Oracle.render` runs its passes compiled (``methods.core.fused``) in static row blocks — the
material-free ones (shading frame, env-map sampling, MIS weights, ray origins, radiance and the sum)
over all samples, the BRDF's sample / pdf / eval per region with its parameters as tensor inputs
(Torrance-Sparrow, whose code needs Python floats, eagerly) — and traces the live shadow rays in one
batch. When every region's BRDF compiles, the passes up to the shadow rays run as one compiled graph per
block of a region's samples (`_pretrace_stage`), laid out samples innermost so that its loops run over
full vectors of samples, and the radiance look-up per block on the env map's channel planes
(`_shade_block_stage`). The light samples' env-map
cells are searched before, in one pass over the frame, by a guide table (`_light_cells`,
``methods.core.envguide``: exactly ``scenes.envmap.count_le``'s cells, ~1 load instead of 18). ``benchmarks/oracle.py`` times both and the shadow-ray test alone.

When every region's BRDF has a C body (Lambert, Phong, Blinn-Phong, Cook-Torrance, Ward) and the C
compiler is there, `Oracle._shade_native` runs all of it but the shadow-ray test as C loops instead
(``methods.oracle.native_rays``: the cell search, the per-ray work, the live rays' gather, the radiance
sum; the same operations from the same random numbers; 1.8× the compiled path's frame, chess and
creature bench, 1 thread); the compiled path above is its fallback and, with the eager estimator, its
test oracle. Its shadow rays go to Mitsuba's ``ray_test`` as written (component planes, the live ones
by the active mask: no gather, no copy), and a frame's large arrays (rays, random numbers, the
G-buffer's gathered rows) are work arrays kept for the next frame (`Oracle._work`: a fresh 100 MB
costs ~30 000 page faults per chess bench frame; ``memory()`` reports them), and the random numbers
come from a C copy of torch's generator (``native_rays.uniform``: the same numbers). Session 31:
1.1–1.3× the session-30 frame, process CPU at 1 thread, the images bit for bit the same.

Session 34: the C loops' shadow rays go to the oracle's own Embree scene (``methods.oracle.embree_rays``,
`OWN_TRACER`; Mitsuba's tracer is its fallback and test oracle): a new pose refits its BVH (~1 ms instead
of `_repose`'s ~11 ms full build) and the live rays are handed to Embree as streams (no dead packet
lanes) — the same blocked flags as Mitsuba's tracer, ray for ray; creature bench P 1.15×, V 1.09×, chess
V 1.15×, L 1.18× process CPU at 1 thread.

Session 35 (or35): the torch work between the C loops went — the C loops read each block's G-buffer rows
themselves (``native_rays.Rows``: positions, normals, ω_o, the geometric normal by face) instead of torch's
gathers, ``native_rays.shade`` writes the estimates straight into the frame's channel-major radiance (resolved
by ``GBuffer.resolve(channels_first=True)``) instead of ``index_copy_``, the sample order and `frame_cost`'s
counts come from one C pass (``native_rays.frame_rows``) instead of a ``nonzero`` per region and `_record`'s
flags, and a frame of the same mesh keeps the per-face geometric normals (`Oracle._face_table`): images and
counts bit for bit those of the torch path, which stays beside them (`DIRECT`, `FRAME_ROWS`, `FACE_CACHE`
off; ``tests/methods/test_oracle_direct.py``). Creature bench V / P 1.09× process CPU at 1 thread
(``benchmarks.oracle_ab``); ``benchmarks.oracle_flags_ab`` 1.07–1.08× at 1 thread, 1.10–1.5× at 2 on a loaded
host (the torch ops' parallel regions wait on a descheduled thread). Tried and dropped (captured rays, 1
thread): Embree's coherent stream flag (0.38×), rtcOccluded1 per ray (0.50×), 16 / 8-ray packets in order (0.77
/ 0.72×), the live rays sorted by direction (0.86–0.92×) or by origin Morton code (0.97×) before the stream,
larger / smaller streams, a one-level HIGH-quality static scene, other Embree ISAs / frequency levels (0.82–1.01×).
Without ``RTC_SCENE_FLAG_ROBUST`` the stream traverses 1.24× faster but its answers are not Mitsuba's: 1
blocked flag of 57 M live rays flipped (chess bench V frame 1; chess V / L / E, creature V / P / E, 5 frames each): kept robust.
"""
from __future__ import annotations

import torch
from torch import Tensor

import math
from dataclasses import fields

from methods.base import GBUFFER_HIT_BYTES, Capabilities, Frame, FrameCost, GBuffer, Method, output_bytes, register
from scenes.sequences import KINDS
from methods.core import native
from methods.oracle import native_rays as oracle_native
from methods.oracle.embree_rays import EmbreeTracer
from methods.core.frames import coordinate_system
from methods.core.latlong import planar_radiance
from methods.core.fused import fused, map_rows
from methods.core.sampling import cosine_hemisphere_pdf, sample_cosine_hemisphere
from methods.core.visibility import Visibility
from references.visibility import MitsubaVisibility, make_visibility, resolve_backend
from methods.core.envguide import fix_unguided, guide_table, guided_count_le, sample_cells_at
from scenes.envmap import bilinear_lookup, cell_pdf, count_le

# Shadow-ray origin offset, as a fraction of the scene's bounding-box diagonal (Mitsuba offsets by
# a relative epsilon too; any value well above float32 round-off of positions and well below
# geometric detail gives the same image).
RAY_EPS_REL = 1e-5

# Frames on the C loops' path trace their shadow rays with the oracle's own tracer (``methods.oracle.embree_rays``:
# a refitted BVH per pose instead of Mitsuba's full build, the live rays as one stream); False: Mitsuba's.
OWN_TRACER = True

# Frames on the C loops' path read the G-buffer rows in the C loops and write the estimates into a channel-major
# radiance (`Oracle._render_direct`, or35); False: the rows gathered by torch and scattered by ``index_copy_``.
DIRECT = True
# `Oracle._render_direct` keeps the per-face geometric normals of the last frame's mesh for a frame of the same mesh
# (`Oracle._face_table`, or35); False: computed every frame.
FACE_CACHE = True
# The frame's sample order and `frame_cost`'s counts by one C pass (``oracle_native.frame_rows``, or35); False: by
# torch (``nonzero`` per region, `Oracle._record`'s flags).
FRAME_ROWS = True


def _direct_ok(gbuffer) -> bool:
    """Whether `Oracle._render_direct` takes this G-buffer's arrays as they are (``oracle_native.Rows``)."""
    return (gbuffer.position.is_contiguous() and gbuffer.normal.is_contiguous() and gbuffer.face.is_contiguous()
            and gbuffer.face.dtype == torch.int64 and gbuffer.wo.dim() == 2
            and all(x.dtype == torch.float32 and x.device.type == "cpu" for x in (gbuffer.position, gbuffer.normal, gbuffer.wo)))


# G-buffer samples per block of the compiled stages (`methods.core.fused.map_rows`): each sample
# carries light_samples + brdf_samples rays, so a block's (rows, rays, 3) temporaries stay a few MB;
# 8 blocks of a bench frame (2^13 rows: 32, and ~0.1 s more of per-call overhead per frame).
ROWS = 1 << 15
# G-buffer samples per block of `_pretrace_stage` (the fused stages of one region): smaller, as each
# region's last block is padded (3 regions on chess).
PRETRACE_ROWS = 1 << 13


def _power_heuristic(pdf_a: Tensor, pdf_b: Tensor) -> Tensor:
    """MIS weight of strategy a (Veach 1997 eq. 9.13, β = 2)."""
    a2, b2 = pdf_a * pdf_a, pdf_b * pdf_b
    return torch.where(a2 > 0, a2 / (a2 + b2), torch.zeros_like(a2))


def geometric_normals(V: Tensor, F: Tensor, face: Tensor) -> Tensor:
    """Unit geometric normals (P, 3) of faces ``face`` (P,) of the mesh (V (N,3), F (M,3))."""
    tri = V[F[face]]  # (P, 3, 3)
    ng = torch.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0], dim=-1)
    return ng / ng.norm(dim=-1, keepdim=True).clamp_min(1e-30)


def _face_normals(V: Tensor, F: Tensor, face: Tensor, hit: Tensor):
    """`geometric_normals` of the faces of G-buffer samples, as a function of sample indices ``sel``
    (rows of ``face``): computed once per face of the mesh and gathered when the frame's hit
    samples (``hit``) outnumber the faces (the same per-face arithmetic, so the same normals),
    else per sample."""
    if hit.numel() <= F.shape[0]:
        return lambda sel: geometric_normals(V, F, face[sel])
    ng = geometric_normals(V, F, torch.arange(F.shape[0], device=F.device))
    return lambda sel: ng.index_select(0, face[sel])


def _repose(vis, V: Tensor, F: Tensor) -> bool:
    """Write the vertex positions V of a new pose into the Mitsuba scene of ``vis`` (a
    ``references.visibility.MitsubaVisibility`` of the same faces F and vertex count: a posed mesh's
    topology does not change) — ``mi.traverse`` of its scene, the mesh's ``vertex_positions``, then
    ``params.update()``, which rebuilds the BVH — and its ``V``, ``bbox``, ``scale`` (``RayCaster``'s
    attributes) to match: the tracer `make_visibility` (V, F) would build, on the same mesh object. False,
    nothing changed, for another tracer (embreex: `make_visibility` builds a new one) or another mesh.
    Mitsuba's and Embree's answer for a ray depends on the triangles only, not on the BVH built over
    them (robust traversal), so the rays see the same hits. Session 33: creature bench P, a pose
    ~14.4 ms CPU instead of ~17.8 ms for a new scene (1 thread), most of both the BVH build."""
    if type(vis) is not MitsubaVisibility:
        return False
    import mitsuba as mi
    import numpy as np

    Vn = V.detach().cpu().numpy().astype(np.float32)
    if Vn.shape != vis.V.shape or not np.isfinite(Vn).all():
        return False
    Fn = F.detach().cpu().numpy()
    if Fn.shape != vis.F.shape or not np.array_equal(Fn, vis.F):
        return False
    params = mi.traverse(vis._scene)
    key = [k for k in params.keys() if k.endswith(".vertex_positions")]
    if len(key) != 1:
        return False
    params[key[0]] = mi.Float(np.ascontiguousarray(Vn).ravel())
    params.update()
    lo, hi = Vn.min(0), Vn.max(0)
    vis.V, vis.bbox = Vn, (lo, hi)
    vis.scale = float(np.linalg.norm(hi - lo)) or 1.0
    return True


def _segments(regions: list, a: int, b: int) -> list:
    """(material, start, end) ranges, relative to a, of the rows [a, b) of samples laid out region
    after region (``regions``: (material, count) in that order)."""
    out, r0 = [], 0
    for mat, q in regions:
        lo, hi = max(a, r0), min(b, r0 + q)
        if lo < hi:
            out.append((mat, lo - a, hi - a))
        r0 += q
    return out


def _dot(a: Tensor, b: Tensor) -> Tensor:
    """a · b over the last axis (3), unrolled."""
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


def _to_local(s: Tensor, t: Tensor, n: Tensor, v: Tensor) -> Tensor:
    """World vectors v (..., 3) → the shading frame (rows s, t, n broadcast against v)."""
    return torch.stack([_dot(s, v), _dot(t, v), _dot(n, v)], -1)


def _rays(x: Tensor, rax: int, n: int) -> Tensor:
    """Per-sample x (Q, ...) broadcast to n rays on the ray axis ``rax`` (0: (n, Q, ...), rays first —
    the compiled frame's layout, `_pretrace_stage`; 1: (Q, n, ...))."""
    return x.unsqueeze(rax).expand(*x.shape[:rax], n, *x.shape[rax:])


def _guide_stage(u, cdf, guide):
    """The env map's cell of each light sample, ``count_le(cdf, u₀)`` by the guide table
    (`methods.core.envguide.guided_count_le`): → (k int32, ok); `Oracle._light_cells` searches the
    rows not ok again."""
    k, ok = guided_count_le(u[..., 0].double(), cdf, guide)
    return k.to(torch.int32), ok


def _light_stage(n, wo, ng, u, k, cdf, p_flat, omega, R64, light: bool, rax: int = 1):
    """The shading frame, ω_o in it, the geometric normal on the shading normal's side, and the
    env-map samples (`scenes.envmap.sample_cells`, its cells k given: `Oracle._light_cells`) in world
    and local coordinates with their densities — `Oracle._shade` up to the BRDF calls. Per-sample
    arrays (Q, 3), per-ray arrays with the rays on axis ``rax`` (`_rays`)."""
    s, t = coordinate_system(n)
    wo_l = _to_local(s, t, n, wo)
    ng = torch.where((_dot(ng, n) < 0).unsqueeze(-1), -ng, ng)
    if not light:
        return wo_l, ng, u, u[..., 0], u
    H, W = omega.shape[0] + 1, p_flat.shape[0] // omega.shape[0]
    d, pdf = sample_cells_at(k, u, cdf, p_flat, omega, R64, H, W)
    d, pdf = d.float(), pdf.float()
    return wo_l, ng, d, pdf, _to_local(s.unsqueeze(rax), t.unsqueeze(rax), n.unsqueeze(rax), d)


def _weight_stage(n, d_l, pdf_l, pdf_bl, wi_ll, wi_b, pdf_b, p2d, omega, R64, nl: int, nb: int, rax: int = 1):
    """World directions of the BRDF samples, the env map's density there (`scenes.envmap.cell_pdf`)
    and every ray's MIS weight / pdf / count (power heuristic): → directions (Q, K, 3) world and
    local, weights (Q, K), light samples first (rays on axis ``rax``: (K, Q, ...) for 0)."""
    ds, wis, ws = [], [], []
    s, t = (x.unsqueeze(rax) for x in coordinate_system(n))
    if nl:
        w = _power_heuristic(pdf_l, pdf_bl) / pdf_l.clamp_min(1e-30) / nl
        ws.append(torch.where(pdf_l > 0, w, torch.zeros_like(w)))
        ds.append(d_l)
        wis.append(wi_ll)
    if nb:
        d = wi_b[..., :1] * s + wi_b[..., 1:2] * t + wi_b[..., 2:] * n.unsqueeze(rax)
        pdf_lb = cell_pdf(d, p2d, omega, R64).float() if nl else torch.zeros_like(pdf_b)
        w = _power_heuristic(pdf_b, pdf_lb) / pdf_b.clamp_min(1e-30) / nb
        ws.append(torch.where(pdf_b > 0, w, torch.zeros_like(w)))
        ds.append(d)
        wis.append(wi_b)
    return torch.cat(ds, rax), torch.cat(wis, rax), torch.cat(ws, rax)


def _ray_stage(f, wi, w, d, p, ng, eps, rax: int = 1):
    """Each ray's contribution f·cos·w (Q, K, 3), whether it is live (non-zero: traced) and its
    shadow-ray origin, offset along the geometric normal to the side of the ray."""
    contrib = f * (wi[..., 2].clamp_min(0.0) * w).unsqueeze(-1)
    live = contrib.amax(-1) > 0
    ng, p = ng.unsqueeze(rax), p.unsqueeze(rax)
    side = torch.sign(_dot(ng, d)).unsqueeze(-1)
    return contrib, live, p + side * ng * eps


def _shade_stage(contrib, lit, d, data, ext, R32):
    """Σ_k contribution · radiance over the rays lit (live and unblocked): (Q, 3). The radiance of
    the others is not looked up (a fixed direction stands in) and counts 0."""
    up = torch.zeros_like(d)
    up[..., 1] = 1.0
    dl = torch.where(lit.unsqueeze(-1), d, up)
    dl = dl[..., :1] * R32[0] + dl[..., 1:2] * R32[1] + dl[..., 2:] * R32[2]  # EnvMap.to_local: d @ R
    L = bilinear_lookup(data, dl, ext)
    L = torch.where(lit.unsqueeze(-1), L, torch.zeros_like(L))
    acc = contrib[:, 0] * L[:, 0]
    for k in range(1, contrib.shape[1]):  # unrolled: one thread per sample whatever K
        acc = acc + contrib[:, k] * L[:, k]
    return acc


# BRDF families whose specular code (``scenes.materials``) takes tensor parameters: compiled once per
# family with the parameters as inputs (a VB sequence changes them every frame). Others
# (Torrance-Sparrow: Python-float normalisation) run eagerly.
_TENSOR_KINDS = ("lambert", "phong", "blinnphong", "cooktorrance", "ward")


def _compiles(mat) -> bool:
    """Whether ``mat``'s BRDF runs compiled: a library material (``scenes.materials``) of a
    `_TENSOR_KINDS` family. Anything else the oracle is given — a subclass elsewhere, or any object
    with eval / pdf / sample (a test's mixture) — runs its own methods eagerly."""
    return type(mat).__module__ == "scenes.materials" and getattr(mat, "kind", None) in _TENSOR_KINDS


class _TensorParams:
    """A material's parameters as float64 0-d tensors (kd, ks: (3,)) for its specular methods called
    on this object under ``torch.compile`` (inputs, not constants: no recompilation per value)."""

    def __init__(self, mat) -> None:
        for f in fields(mat):
            setattr(self, f.name, torch.tensor(getattr(mat, f.name), dtype=torch.float64))
        self.ps = torch.tensor(mat.spec_weight, dtype=torch.float64)

    def _ks(self, like: Tensor) -> Tensor:
        return self.ks.to(like.dtype)


def _mix_pdf(cls, P, has_spec: bool, wi: Tensor, wo: Tensor) -> Tensor:
    """``Material.pdf`` on tensor parameters P (`_TensorParams`)."""
    p = (1.0 - P.ps) * cosine_hemisphere_pdf(wi)
    if has_spec:
        p = p + P.ps * cls._spec_pdf(P, wi, wo)
    return p.to(wi.dtype)


def _brdf_sample_stage(wo_l, u_b, wi_ll, cls, P, has_spec: bool, nl: int, nb: int, rax: int = 1):
    """The BRDF's density at the light samples and its own samples (``Material.pdf`` and
    ``Material.sample`` on tensor parameters) for rows of one region (rays on axis ``rax``)."""
    out = []
    if nl:
        out.append(_mix_pdf(cls, P, has_spec, wi_ll, _rays(wo_l, rax, nl)))
    if nb:
        wo = _rays(wo_l, rax, nb)
        pd = 1.0 - P.ps
        u0, u1 = u_b[..., 0], u_b[..., 1]
        one_minus = 1.0 - torch.finfo(u_b.dtype).eps
        wi = sample_cosine_hemisphere(torch.stack([(u0 / pd.clamp_min(1e-12)).clamp(0, one_minus), u1], -1))[0]
        if has_spec:
            us = torch.stack([((u0 - pd) / P.ps).clamp(0, one_minus), u1], -1)
            wi = torch.where((u0 >= pd)[..., None], cls._spec_sample(P, wo, us), wi)
        out += [wi, _mix_pdf(cls, P, has_spec, wi, wo)]
    return tuple(out)


def _brdf_eval_stage(wi, wo_l, cls, P, rax: int = 1):
    """``Material.eval`` on tensor parameters for rows of one region: (Q, K, 3) (rays on axis ``rax``)."""
    wo = wo_l.unsqueeze(rax).expand_as(wi)
    f = P.kd.to(wi.dtype) / math.pi + cls._spec_eval(P, wi, wo)
    up = (wi[..., 2] > 0) & (wo[..., 2] > 0)
    return torch.where(up[..., None], f, torch.zeros_like(f))


def _pretrace_stage(n, wo, ng, p, u_l, k_l, u_b, cdf, p_flat, p2d, omega, R64, eps, cls, P, has_spec: bool,
                    nl: int, nb: int):
    """`_light_stage`, `_brdf_sample_stage`, `_weight_stage`, `_brdf_eval_stage` and `_ray_stage` of a
    block of B samples of one region (a material that compiles, `_compiles`) in one compiled graph,
    the samples innermost (`_soa_blocks`): n, wo, ng, p (3, B), u_l / u_b (NL / NB, 2, B), k_l (NL, B)
    → contributions f·cos·w (K, B, 3), live (K, B), shadow-ray origins and world directions (K, B, 3)
    (rays first: `_rays` with axis 0). Inductor's loops then run over the B samples in full vectors;
    with the rays innermost ((Q, K, 3), session 17) they ran over the K = 4-8 rays of a sample (4-8 of
    16 lanes). Compiled without Inductor's tiling heuristics, which left loops over the 3 components
    (`OPTIONS`). Placeholders where a strategy is off, as `Oracle._shade_fast`; the stages' eager
    functions (``.eager``: traced into this one graph)."""
    n, wo, ng, p = n.t(), wo.t(), ng.t(), p.t()
    u_l, u_b = u_l.transpose(1, 2), u_b.transpose(1, 2)
    wo_l, ng, d_l, pdf_l, wi_ll = _light_stage.eager(n, wo, ng, u_l, k_l, cdf, p_flat, omega, R64, nl > 0, 0)
    res = _brdf_sample_stage.eager(wo_l, u_b, wi_ll, cls, P, has_spec, nl, nb, 0)
    pdf_bl = res[0] if nl else pdf_l
    wi_b, pdf_b = res[-2:] if nb else (wi_ll, pdf_l)
    d, wi, w = _weight_stage.eager(n, d_l, pdf_l, pdf_bl, wi_ll, wi_b, pdf_b, p2d, omega, R64, nl, nb, 0)
    f = _brdf_eval_stage.eager(wi, wo_l, cls, P, 0)
    contrib, live, o = _ray_stage.eager(f, wi, w, d, p, ng, eps, 0)
    return contrib, live, o, d


def _shade_block_stage(contrib, lit, d, planes, R32, H: int, W: int):
    """`_shade_stage` of a block in `_pretrace_stage`'s layout (contributions and world directions
    (K, B, 3), lit (K, B) → (B, 3)), the radiance per channel on the env map's channel planes
    (``methods.core.latlong.planar_radiance``: op for op ``scenes.envmap.bilinear_lookup``), so the
    loop runs over the B samples with vectorised atan2 / acos instead of over the 3 channels."""
    lit_f = lit.float()
    x = torch.where(lit, d[..., 0], torch.zeros_like(lit_f))  # the unlit: a fixed direction, +y
    y = torch.where(lit, d[..., 1], torch.ones_like(lit_f))
    z = torch.where(lit, d[..., 2], torch.zeros_like(lit_f))
    xl, yl, zl = (x * R32[0, c] + y * R32[1, c] + z * R32[2, c] for c in range(3))  # EnvMap.to_local: d @ R
    acc = []
    for c, L in enumerate(planar_radiance(xl, yl, zl, planes, H, W)):
        L = torch.where(lit, L, torch.zeros_like(L))
        a = contrib[0, :, c] * L[0]
        for k in range(1, contrib.shape[0]):  # unrolled, the order of `_shade_stage`
            a = a + contrib[k, :, c] * L[k]
        acc.append(a)
    return torch.stack(acc, -1)


def _soa_blocks(x: Tensor, B: int) -> Tensor:
    """Per-sample rows x (nb·B, ...) → (nb, ..., B) contiguous: blocks of B samples, the samples
    innermost (`_pretrace_stage`'s layout)."""
    x = x.reshape(-1, B, *x.shape[1:])
    return x.permute(0, *range(2, x.dim()), 1).contiguous()


# `_pretrace_stage`'s Inductor options: no tiling heuristics (they chose loops over the 3 components
# of its (K, B, 3) temporaries, scalar: 417 → 323 ms of a chess bench frame, 1 thread); its gathers
# (env-map tables) are in range by construction (clamped cells). 256-bit vectors (``cpp.simdlen``; the
# default is the host's widest, 512 on AVX-512): its loops are full of strided loads and gathers
# (the (K, B, 3) components), which 16-lane vectors assemble element by element through a temporary
# buffer — ms per 8192-sample block, 1 thread, compiled alone on a chess frame's captured blocks:
# Blinn-Phong 8.5 → 7.9, Cook-Torrance 9.6 → 7.6, Phong 9.3 → 8.6 (the same numbers, bit for bit).
# Other hosts keep Inductor's default (None): an explicit 256 on a host without AVX2 would leave the
# loops scalar.
OPTIONS = {"cpp.enable_tiling_heuristics": False, "assert_indirect_indexing": False,
           "cpp.simdlen": 256 if native.cpu_capability() == "AVX512" else None}
_pretrace_stage = fused(_pretrace_stage, options=OPTIONS)
_brdf_sample_stage = fused(_brdf_sample_stage)
_brdf_eval_stage = fused(_brdf_eval_stage)
_light_stage = fused(_light_stage)
_guide_stage = fused(_guide_stage, options={"assert_indirect_indexing": False})
_weight_stage = fused(_weight_stage)
_ray_stage = fused(_ray_stage)
_shade_stage = fused(_shade_stage)
_shade_block_stage = fused(_shade_block_stage, options={"assert_indirect_indexing": False})


@register
class Oracle(Method):
    """Brute-force MIS direct lighting on the G-buffer (no precomputation, no approximation)."""

    name = "oracle"
    capabilities = Capabilities(dynamic_lighting=True, dynamic_brdf=True,
                                dynamic_geometry=True, max_bounces=0)

    def __init__(self, *, light_samples: int = 32, brdf_samples: int = 32, seed: int = 0,
                 max_rays_per_batch: int = 1 << 21) -> None:
        for k, v in (("light_samples", light_samples), ("brdf_samples", brdf_samples)):
            if not isinstance(v, int) or v < 0:
                raise ValueError(f"{k} must be a non-negative int, got {v!r}")
        if light_samples + brdf_samples == 0:
            raise ValueError("light_samples + brdf_samples must be > 0")
        super().__init__(light_samples=light_samples, brdf_samples=brdf_samples, seed=seed)
        self.n_light = light_samples      # env-map samples per G-buffer sample
        self.n_brdf = brdf_samples        # BRDF samples per G-buffer sample
        self.seed = seed
        self.max_rays = max_rays_per_batch
        self.scene = None
        self._vis: tuple[str, Visibility] | None = None  # (pose key, embree scene of that pose)
        # (pose key, the oracle's own tracer of that pose: `methods.oracle.embree_rays`) of the frames on the
        # C loops' path; False once it could not be built (Mitsuba's tracer then)
        self._own: tuple[str, EmbreeTracer] | bool | None = None
        # (P, hit samples, live rays, faces hit, their vertices, env map (H, W)) of the last render (frame_cost)
        self._last: tuple | None = None
        # per-frame work arrays by name, reused by the next frame of the same sizes (`_work`): fresh
        # ones cost their first touch, ~30 000 page faults (~120 MB) per chess bench frame
        self._scratch: dict[str, Tensor] = {}
        # the mesh whose per-face normals ``_scratch["face_normals"]`` holds (`_face_table`) and its tensors
        self._face_key: tuple | None = None
        self._face_refs: tuple = ()

    # -- interface ----------------------------------------------------------------------------
    def precompute(self, scene) -> None:
        self.scene = scene

    def memory(self) -> dict[str, int]:
        """Nothing precomputed; kept between frames: the tracer's scene of the current pose (Mitsuba's, or the
        oracle's own on the C loops' path: its BVH and a copy of the vertices; not counted)
        and the last frame's work arrays (`_work`, reused by the next frame)."""
        return {f"work:{k}": v.numel() * v.element_size() for k, v in self._scratch.items()}

    def _work(self, name: str, shape: tuple, dtype=torch.float32) -> Tensor:
        """A work array of this shape and dtype, contiguous: the leading elements of the one kept under
        ``name`` when it is large enough (as the last frame left them; its pages are mapped already,
        where a fresh large array is page-faulted in on first touch and returned to the system when
        freed — and a frame's sizes follow its hit samples, which move with the view), else of a new
        one, zeros, 1/8 larger (a slowly growing hit count does not allocate every frame)."""
        n = math.prod(int(x) for x in shape)
        t = self._scratch.get(name)
        if t is None or t.numel() < n or t.dtype != dtype:
            self._scratch.pop(name, None)
            t = self._scratch[name] = torch.zeros(n + n // 8, dtype=dtype)
        return t[:n].view(*shape)

    @staticmethod
    def _pose_key(pose: Tensor | None) -> str:
        return "rest" if pose is None else repr(pose.detach().cpu().tolist())

    def _own_tracer(self, geom, pose: Tensor | None) -> EmbreeTracer | None:
        """The oracle's own tracer (``methods.oracle.embree_rays``) of a frame on the C loops' path: the last
        one when the pose is the same, else the last one with this pose's vertices written into it (a
        refit of its BVH instead of `_repose`'s full build), else a new one; None — Mitsuba's tracer
        (`_visibility`) then — when `OWN_TRACER` is off, ``PRTBENCH_VISIBILITY`` does not choose Mitsuba
        (whose answers it gives), or it cannot be built."""
        if self._own is False or not OWN_TRACER or resolve_backend() != "mitsuba":
            return None
        key = self._pose_key(pose)
        if self._own is None or self._own[0] != key:
            tracer = self._own[1] if self._own is not None else None
            if tracer is None or not tracer.repose(geom.V, geom.F):
                tracer = EmbreeTracer.create(geom.V, geom.F)
            if tracer is None:
                self._own = False
                return None
            self._own = (key, tracer)
        return self._own[1]

    def _visibility(self, geom, pose: Tensor | None) -> Visibility:
        """The tracer of the frame's pose: the last one when the pose is the same, else the last one's
        Mitsuba scene with this pose's vertex positions written into it (`_repose`), else a new one."""
        key = self._pose_key(pose)
        if self._vis is None or self._vis[0] != key:
            vis = self._vis[1] if self._vis is not None else None
            if vis is None or not _repose(vis, geom.V, geom.F):
                vis = make_visibility(geom.V, geom.F)
            self._vis = (key, vis)
        return self._vis[1]

    def _frame_setup(self, frame: Frame, tracer: bool = True):
        """(geometry of the frame's pose, its tracer (None unless ``tracer``), shadow-ray offset, the
        frame's generator)."""
        if self.scene is None:
            raise RuntimeError("call precompute(scene) before render()")
        geom = self.scene.geometry(frame.pose)
        vis = self._visibility(geom, frame.pose) if tracer else None
        extent = (geom.V.max(0).values - geom.V.min(0).values).norm().item()
        eps = RAY_EPS_REL * max(extent, 1e-6)
        gen = torch.Generator().manual_seed(int(self.seed) * 1_000_003 + int(frame.index))
        return geom, vis, eps, gen

    def _record(self, gbuffer: GBuffer, geom, hit_idx: Tensor | tuple, live: int, env) -> None:
        """`frame_cost`'s counts of the frame: the faces hit and their distinct vertices, counted by
        marking them in per-face / per-vertex flags (what ``torch.unique`` counted, without its sort:
        33 ms of a 600 ms chess frame, 1 thread); ``hit_idx`` a tuple: (hit samples, faces, vertices) as
        ``oracle_native.frame_rows`` counted them."""
        if isinstance(hit_idx, tuple):  # (hit samples, faces, vertices) counted by `oracle_native.frame_rows`
            self._last = (gbuffer.num_samples, hit_idx[0], live, hit_idx[1], hit_idx[2],
                          tuple(int(x) for x in env.data.shape[:2]))
            return
        M, N = geom.F.shape[0], geom.V.shape[0]
        hit_face = torch.zeros(M, dtype=torch.bool, device=geom.F.device)
        hit_face[gbuffer.face[hit_idx]] = True
        faces = torch.nonzero(hit_face).squeeze(-1)
        hit_vert = torch.zeros(N, dtype=torch.bool, device=geom.F.device)
        hit_vert[geom.F[faces].reshape(-1)] = True
        self._last = (gbuffer.num_samples, int(hit_idx.numel()), live, int(faces.numel()),
                      int(hit_vert.sum()), tuple(int(x) for x in env.data.shape[:2]))

    def render_reference(self, frame: Frame, gbuffer: GBuffer) -> Tensor:
        """The eager estimator (`_shade` per region and chunk of samples): the test oracle of
        `render`, which computes the same estimate from the same random numbers in compiled stages."""
        geom, vis, eps, gen = self._frame_setup(frame)
        out = torch.zeros(gbuffer.num_samples, 3, dtype=torch.float32)
        hit_idx = torch.nonzero(gbuffer.hit, as_tuple=False).squeeze(-1)
        chunk = self._chunk()
        live = [0]
        for r, region in enumerate(self.scene.regions):
            mat = frame.materials[region]
            idx = hit_idx[gbuffer.region[hit_idx] == r]
            for c0 in range(0, idx.numel(), chunk):
                sel = idx[c0:c0 + chunk]
                out[sel] = self._shade(mat, frame.envmap, vis, eps,
                                       gbuffer.position[sel], gbuffer.normal[sel], gbuffer.wo[sel],
                                       geometric_normals(geom.V, geom.F, gbuffer.face[sel]), gen, live)
        self._record(gbuffer, geom, hit_idx, live[0], frame.envmap)
        return gbuffer.resolve(out)

    def _chunk(self) -> int:
        """G-buffer samples per batch of rays (at most ``max_rays_per_batch`` rays)."""
        return max(1, self.max_rays // (self.n_light + self.n_brdf))

    def render(self, frame: Frame, gbuffer: GBuffer) -> Tensor:
        """`render_reference`'s estimate, its material-free passes compiled (`_light_stage`,
        `_weight_stage`, `_ray_stage`, `_shade_stage`, ``methods.core.fused``) and one shadow-ray
        batch per ``max_rays_per_batch`` rays: the samples are taken region by region, the random
        numbers drawn in the reference's order, the BRDF's sample/pdf/eval (Python-level
        parameters) stay eager per region."""
        geom, _, eps, gen = self._frame_setup(frame, tracer=False)
        env, NL, NB = frame.envmap, self.n_light, self.n_brdf
        chunk = self._chunk()
        R = len(self.scene.regions)
        # the samples and frame_cost's counts by one C pass (`oracle_native.frame_rows`), else by torch below
        fr = oracle_native.frame_rows(gbuffer.hit, gbuffer.region, gbuffer.face, R, geom.F, geom.V.shape[0],
                                      self._work) if FRAME_ROWS and R else None
        if fr is not None:
            order, counts, hits, n_faces, n_verts = fr
            regions = [(frame.materials[region], c) for region, c in zip(self.scene.regions, counts)]
            hit_idx = (hits, n_faces, n_verts)  # `_record`'s counts, counted
        else:
            hit_idx = torch.nonzero(gbuffer.hit, as_tuple=False).squeeze(-1)
            # each region's hit samples, ascending (= hit_idx[region[hit_idx] == r], without its gathers)
            order = [torch.nonzero((gbuffer.region == r) & gbuffer.hit).squeeze(-1) for r in range(R)]
            regions = [(frame.materials[region], idx.numel()) for region, idx in zip(self.scene.regions, order)]
            order = torch.cat(order) if order else hit_idx
        # the reference's draws, per region and chunk, straight into the frame's (Q, NL / NB, 2) arrays
        # (a work array: `_work`; the same numbers as drawn apart and concatenated)
        Q = order.numel()
        U_l = self._work("U_l", (Q, NL, 2)) if NL else torch.zeros(Q, 1, 2)
        U_b = self._work("U_b", (Q, NB, 2)) if NB else torch.zeros(Q, 1, 2)
        draws, row = [], 0
        for _, q_r in regions:
            for c0 in range(0, q_r, chunk):
                q = min(chunk, q_r - c0)
                draws += ([U_l[row:row + q]] if NL else []) + ([U_b[row:row + q]] if NB else [])
                row += q
        if not oracle_native.uniform(gen, draws):  # the C generator: torch.rand's numbers, faster
            for x in draws:
                torch.rand(x.shape, generator=gen, out=x)
        cdf, p, omega = env._tables()
        vis = None
        if self._native(regions, gbuffer, U_l, U_b):  # the C loops search the cells themselves
            K_l = None
            vis = self._own_tracer(geom, frame.pose)
        else:
            K_l = self._light_cells(U_l, cdf) if NL else torch.zeros(U_l.shape[:2], dtype=torch.int32)
        if vis is None:
            vis = self._visibility(geom, frame.pose)
        tables = (cdf, p.reshape(-1), p, omega, env.to_world.to(torch.float64), env.periodic_texels(planes=True))
        ext, R32 = env.periodic_texels(), env.to_world.to(torch.float32)
        eps_t = torch.tensor(eps, dtype=torch.float32)
        if K_l is None and DIRECT and _direct_ok(gbuffer):  # the C loops read the G-buffer rows themselves
            return self._render_direct(gbuffer, geom, order, regions, hit_idx, chunk, vis, eps_t, U_l, U_b, tables,
                                       env, ext, R32)
        out = torch.zeros(gbuffer.num_samples, 3, dtype=torch.float32)
        face_ng = _face_normals(geom.V, geom.F, gbuffer.face, order)
        live_total = 0
        for a in range(0, order.numel(), chunk):
            sel = order[a:a + chunk]
            mats = _segments(regions, a, a + sel.numel())
            o, live_n = self._shade_fast(mats, vis, eps_t, *self._gather(gbuffer, sel), face_ng(sel),
                                         U_l[a:a + chunk], None if K_l is None else K_l[a:a + chunk], U_b[a:a + chunk],
                                         tables, env.data,
                                         ext, R32)
            out.index_copy_(0, sel, o)
            live_total += live_n
        self._record(gbuffer, geom, hit_idx, live_total, env)
        return gbuffer.resolve(out)

    def _render_direct(self, gbuffer: GBuffer, geom, order: Tensor, regions: list, hit_idx: Tensor, chunk: int, vis,
                       eps_t: Tensor, U_l: Tensor, U_b: Tensor, tables: tuple, env, ext: Tensor, R32: Tensor) -> Tensor:
        """`render`'s C-loop frame without its torch gathers and scatter (or35): `_shade_native` on the
        G-buffer's own arrays (``oracle_native.Rows``: each block's positions, normals, ω_o and geometric normals
        read by the C loops from the samples' rows, the values `_gather` and `_face_normals` give) and the
        estimates written by ``oracle_native.shade`` straight into the frame's channel-major radiance (a work
        array, zero at misses), resolved by ``GBuffer.resolve(channels_first=True)`` — the same image, bit for
        bit, as `_gather` / ``index_copy_`` / ``resolve`` (``tests/methods/test_oracle.py``)."""
        planes = self._work("radiance", (3, gbuffer.num_samples)).zero_()
        if order.numel() <= geom.F.shape[0]:  # `_face_normals`' choice: per sample, else per face gathered
            ng, face = geometric_normals(geom.V, geom.F, gbuffer.face[order]), None
        else:
            ng, face = self._face_table(geom), gbuffer.face
        rows = oracle_native.Rows(order, gbuffer.position, gbuffer.normal, gbuffer.wo, ng.contiguous(), face)
        live_total = 0
        for a in range(0, order.numel(), chunk):
            b = min(a + chunk, order.numel())
            mats = _segments(regions, a, b)
            live_total += self._shade_native(mats, vis, eps_t, rows[a:b], None, None, None, U_l[a:b], U_b[a:b],
                                             tables, env.data, ext, R32, into=planes)
        self._record(gbuffer, geom, hit_idx, live_total, env)
        return gbuffer.resolve(planes, channels_first=True)

    def _face_table(self, geom) -> Tensor:
        """`geometric_normals` of every face of the frame's mesh (F, 3), as `_face_normals` computes them: kept
        from the last frame (a work array, ``memory()``) while the mesh is the same tensors, unmodified (the
        scene's geometry of the same pose: a static scene's V / L / E / VB frames; ``_version`` counts in-place
        writes), else computed again (a new pose) — the same values either way (or35: ~1.7 ms CPU a
        creature bench frame)."""
        key = (id(geom.V), geom.V._version, id(geom.F), geom.F._version, tuple(geom.V.shape), tuple(geom.F.shape))
        t = self._scratch.get("face_normals")
        if t is None or self._face_key != key or t.shape != (geom.F.shape[0], 3) or not FACE_CACHE:
            ng = geometric_normals(geom.V, geom.F, torch.arange(geom.F.shape[0], device=geom.F.device))
            self._scratch["face_normals"] = t = ng.contiguous()
            self._face_key = key if FACE_CACHE else None
            self._face_refs = (geom.V, geom.F)  # the keyed tensors stay alive: their ids are not reused
        return t

    def _gather(self, gbuffer: GBuffer, sel: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """The G-buffer's positions, normals and ω_o of the samples ``sel``, ``index_select``ed into work
        arrays (`_work`; CPU) — the values of ``position[sel]`` etc."""
        out = []
        for name in ("position", "normal", "wo"):
            x = getattr(gbuffer, name)
            if x.device.type != "cpu":
                out.append(x[sel])
                continue
            w = self._work(name, (sel.numel(), *x.shape[1:]), x.dtype)
            if x.is_contiguous():
                out.append(torch.index_select(x, 0, sel, out=w))
            elif x.dim() == 2 and x.t().is_contiguous():  # channel planes (ω_o's (3, P) transposed): 12 → 1.7 ms
                w.t().copy_(x.t().index_select(1, sel))
                out.append(w)
            else:
                out.append(w.copy_(x[sel]))
        return tuple(out)

    @staticmethod
    def _light_cells(U_l: Tensor, cdf: Tensor) -> Tensor:
        """The env-map cell (Q, NL) int32 of each light sample's uniforms U_l (Q, NL, 2): ``count_le(cdf,
        u₀)`` (``scenes.envmap.sample_cells``' search) by the guide table in one compiled pass
        (`_guide_stage`), the few samples it does not bracket searched again by ``count_le``."""
        Q, NL = U_l.shape[:2]
        k = torch.empty(Q, NL, dtype=torch.int32, device=U_l.device)
        ok = torch.empty(Q, NL, dtype=torch.bool, device=U_l.device)
        map_rows(_guide_stage, [U_l], (cdf, guide_table(cdf)), chunk=ROWS, out=(k, ok))
        fix_unguided(k, ok, U_l.view(-1, 2)[:, 0], cdf, count_le)  # (Q·NL,) u₀, a strided view
        return k

    def _shade_fast(self, mats, vis, eps: Tensor, p, n, wo, ng, U_l, K_l, U_b, tables, data, ext, R32):
        """`_shade` on samples of several regions (``mats``: (material, start, end) row ranges; K_l the
        light samples' env-map cells, `_light_cells`): → ((Q, 3) estimates, live rays)."""
        NL, NB = self.n_light, self.n_brdf
        cdf, p_flat, p2d, omega, R64 = tables[:5]
        if K_l is None:  # `_native`: the C loops
            return self._shade_native(mats, vis, eps, p, n, wo, ng, U_l, U_b, tables, data, ext, R32)
        if all(_compiles(mat) for mat, _, _ in mats):  # one kernel per block up to the shadow rays
            return self._shade_blocks(mats, vis, eps, p, n, wo, ng, U_l, K_l, U_b, tables, data, ext, R32)
        wo_l, ng, d_l, pdf_l, wi_ll = map_rows(_light_stage, [n, wo, ng, U_l, K_l],
                                                     (cdf, p_flat, omega, R64, NL > 0), chunk=ROWS)
        Q = p.shape[0]
        pdf_bl = torch.empty(Q, NL) if NL else pdf_l
        wi_b = torch.empty(Q, NB, 3) if NB else wi_ll
        pdf_b = torch.empty(Q, NB) if NB else pdf_l
        for mat, a, b in mats:  # the BRDF's density of the light samples and its own samples
            if _compiles(mat):
                P = _TensorParams(mat)
                res = map_rows(_brdf_sample_stage, [wo_l[a:b], U_b[a:b], wi_ll[a:b]],
                               (type(mat), P, mat.spec_weight > 0, NL, NB), chunk=ROWS)
                if NL:
                    pdf_bl[a:b] = res[0]
                if NB:
                    wi_b[a:b], pdf_b[a:b] = res[-2:]
                continue
            if NL:
                pdf_bl[a:b] = mat.pdf(wi_ll[a:b], wo_l[a:b].unsqueeze(1).expand(b - a, NL, 3))
            if NB:
                wi_b[a:b], pdf_b[a:b] = mat.sample(wo_l[a:b].unsqueeze(1).expand(b - a, NB, 3), U_b[a:b])
        d, wi, w = map_rows(_weight_stage, [n, d_l, pdf_l, pdf_bl, wi_ll, wi_b, pdf_b],
                            (p2d, omega, R64, NL, NB), chunk=ROWS)
        f = torch.empty_like(wi)
        for mat, a, b in mats:
            if _compiles(mat):
                f[a:b] = map_rows(_brdf_eval_stage, [wi[a:b], wo_l[a:b]], (type(mat), _TensorParams(mat)), chunk=ROWS)
                continue
            f[a:b] = mat.eval(wi[a:b], wo_l[a:b].unsqueeze(1).expand_as(wi[a:b]))
        contrib, live, o = map_rows(_ray_stage, [f, wi, w, d, p, ng], (eps,), chunk=ROWS)
        return self._trace_shade(vis, contrib, live, o, d, data, ext, R32)

    @staticmethod
    def _native(regions: list, gbuffer: GBuffer, U_l: Tensor, U_b: Tensor) -> bool:
        """Whether a frame runs the C loops (``methods.oracle.native_rays``): they are built, every region's
        BRDF has a C body, the G-buffer and the random numbers are float32 CPU tensors."""
        ts = (gbuffer.position, gbuffer.normal, gbuffer.wo, U_l, U_b)
        return (all(oracle_native.supports(mat) for mat, _ in regions) and oracle_native.available()
                and all(t.dtype == torch.float32 and t.device.type == "cpu" for t in ts))

    def _shade_native(self, mats, vis, eps: Tensor, p, n, wo, ng, U_l, U_b, tables, data, ext, R32, into=None):
        """`_shade_fast` by the C loops of ``methods.oracle.native_rays`` (every region's BRDF has a C body):
        each region's rays (`oracle_native.pretrace`), the live ones traced in one batch
        (`_trace_soa`), the radiance look-up and sum (`oracle_native.shade`): → ((Q, 3) estimates,
        live rays). ``p`` an ``oracle_native.Rows`` (n, wo, ng None) and ``into`` a (3, P) channel-major
        radiance: the rows read from the G-buffer by the C loops and the estimates written into ``into``
        at the samples' rows (`_render_direct`) → live rays."""
        NL, NB = self.n_light, self.n_brdf
        rows = p if isinstance(p, oracle_native.Rows) else None
        K, Q = NL + NB, (rows.idx if rows is not None else p).shape[0]
        cdf, p_flat, _, omega, R64 = tables[:5]
        H, W = data.shape[:2]
        tab = tuple(x.contiguous() for x in (cdf, p_flat, omega, R64))
        U_l, U_b = U_l.contiguous(), U_b.contiguous()
        if rows is None:
            p, n, wo, ng = (x.contiguous() for x in (p, n, wo, ng))
        # rays slot-major; origins and directions as component planes, the shadow-ray tracer's input
        contrib = self._work("contrib", (K, Q, 3))
        o, d = (oracle_native.plane_views(self._work(x, (3 * oracle_native.plane_stride(K * Q),)), K, Q)
                for x in ("origins", "directions"))
        live, blocked = (self._work(x, (K, Q), torch.bool) for x in ("live", "blocked"))
        for mat, a, b in mats:
            src = (rows[a:b], None, None, None) if rows is not None else (n[a:b], wo[a:b], ng[a:b], p[a:b])
            oracle_native.pretrace(mat, *src, U_l[a:b], U_b[a:b], NL, NB, tab,
                                   H, W, float(eps), (contrib[:, a:b], live[:, a:b], o[..., a:b], d[..., a:b]))
        if isinstance(vis, EmbreeTracer):  # the oracle's own tracer (`_own_tracer`)
            n_live = vis.trace(live, o, d, blocked, oracle_native._threads(K * Q))
        else:
            n_live = oracle_native.trace(vis, live, o, d, blocked)
        if rows is not None:
            oracle_native.shade(contrib, live, blocked, d, ext.contiguous(), R32.contiguous(), H, W, into=(rows.idx, into))
            return n_live
        return oracle_native.shade(contrib, live, blocked, d, ext.contiguous(), R32.contiguous(), H, W), n_live

    def _shade_blocks(self, mats, vis, eps: Tensor, p, n, wo, ng, U_l, K_l, U_b, tables, data, ext, R32):
        """`_shade_fast` when every region's BRDF compiles: each region's samples in blocks of
        ``PRETRACE_ROWS`` (the last one padded by repeating its last sample, whose rays are then
        dropped) laid out samples innermost (`_soa_blocks`), one `_pretrace_stage` call per block, the
        live rays traced in one batch, `_shade_block_stage` per block: → ((Q, 3) estimates, live rays).
        ``tables``: the env map's sampling tables and its channel planes (``periodic_texels(planes=True)``)."""
        NL, NB, B = self.n_light, self.n_brdf, PRETRACE_ROWS
        cdf, p_flat, p2d, omega, R64 = tables[:5]
        K, dev = NL + NB, p.device
        H, W = data.shape[:2]
        planes = tables[-1]
        idx, nblk = [], []
        for _, a, b in mats:  # rows of the padded blocks: each region's, its last row repeated
            m = -(-(b - a) // B)
            idx += [torch.arange(a, b, device=dev), torch.full((m * B - (b - a),), b - 1, device=dev)]
            nblk.append(m)
        idx = torch.cat(idx)
        valid = torch.cat([torch.arange(m * B, device=dev) < b - a for (_, a, b), m in zip(mats, nblk)])
        rows = [_soa_blocks(x.index_select(0, idx), B) for x in (n, wo, ng, p, U_l, K_l, U_b)]
        T = len(valid) // B
        contrib, o, d = (torch.empty(T, K, B, 3, device=dev) for _ in range(3))
        live = torch.empty(T, K, B, dtype=torch.bool, device=dev)
        i = 0
        for (mat, _, _), m in zip(mats, nblk):
            args = (cdf, p_flat, p2d, omega, R64, eps, type(mat), _TensorParams(mat), mat.spec_weight > 0, NL, NB)
            for _ in range(m):
                res = _pretrace_stage(*(x[i] for x in rows), *args)
                for dst, x in zip((contrib, live, o, d), res):
                    dst[i] = x
                i += 1
        live &= valid.view(T, 1, B)  # the padding's rays: not traced, not counted
        lit, n_live = self._trace_soa(vis, live, o, d)
        out = torch.empty(T, B, 3, device=dev)
        for i in range(T):
            out[i] = _shade_block_stage(contrib[i], lit[i], d[i], planes, R32, H, W)
        return out.view(-1, 3)[valid], n_live

    @staticmethod
    def _trace_soa(vis, live, o, d):
        """The live rays of blocks (live (T, K, B); origins and directions (T, K, B, 3)) traced in one
        batch: → (lit = live and unblocked, number of live rays)."""
        rays = torch.nonzero(live.view(-1)).squeeze(-1)
        if not rays.numel():
            return live, 0
        blocked = torch.zeros(live.numel(), dtype=torch.bool, device=live.device)
        blocked[rays] = torch.as_tensor(vis.occluded(o.view(-1, 3).index_select(0, rays),
                                                     d.view(-1, 3).index_select(0, rays)), device=live.device)
        return live & ~blocked.view(live.shape), int(rays.numel())

    @staticmethod
    def _trace_shade(vis, contrib, live, o, d, data, ext, R32):
        """The live rays (contributions (Q, K, 3), live (Q, K), origins and world directions
        (Q, K, 3)) traced in one batch and Σ contribution · radiance over the unblocked ones:
        → ((Q, 3), live rays)."""
        rays = torch.nonzero(live.view(-1)).squeeze(-1)
        lit = live
        if rays.numel():
            blocked = torch.zeros(live.numel(), dtype=torch.bool)
            blocked[rays] = torch.as_tensor(vis.occluded(o.view(-1, 3).index_select(0, rays),
                                                         d.view(-1, 3).index_select(0, rays)))
            lit = live & ~blocked.view(live.shape)
        return map_rows(_shade_stage, [contrib, lit, d], (data, ext, R32), chunk=ROWS), int(rays.numel())

    # -- the estimator ------------------------------------------------------------------------
    def _shade(self, mat, env, vis: Visibility, eps: float, p: Tensor, n: Tensor, wo: Tensor,
               ng: Tensor, gen: torch.Generator, live_count: list[int] | None = None) -> Tensor:
        """MIS direct-lighting estimate for samples p, n, wo, ng: (Q, 3) each → (Q, 3). Adds the
        number of live rays (traced: a non-zero contribution) to ``live_count[0]``."""
        Q = p.shape[0]
        s, t = coordinate_system(n)
        frame = torch.stack([s, t, n], dim=-2)  # (Q, 3, 3) world → local rows
        wo_l = (frame @ wo.unsqueeze(-1)).squeeze(-1)
        ng = torch.where(((ng * n).sum(-1, keepdim=True) < 0), -ng, ng)  # same side as shading n

        dirs, weights = [], []
        if self.n_light:
            u = torch.rand(Q, self.n_light, 2, generator=gen)
            d, pdf_l = env.sample(u.view(-1, 2))                       # world dirs, solid-angle pdf
            d, pdf_l = d.view(Q, self.n_light, 3), pdf_l.view(Q, self.n_light)
            wi_l = (frame.unsqueeze(1) @ d.unsqueeze(-1)).squeeze(-1)  # (Q, NL, 3)
            pdf_b = mat.pdf(wi_l, wo_l.unsqueeze(1).expand_as(wi_l))
            w = _power_heuristic(pdf_l, pdf_b) / pdf_l.clamp_min(1e-30) / self.n_light
            w = torch.where(pdf_l > 0, w, torch.zeros_like(w))
            dirs.append((d, wi_l)); weights.append(w)
        if self.n_brdf:
            u = torch.rand(Q, self.n_brdf, 2, generator=gen)
            wo_rep = wo_l.unsqueeze(1).expand(Q, self.n_brdf, 3)
            wi_l, pdf_b = mat.sample(wo_rep, u)
            d = (frame.transpose(-1, -2).unsqueeze(1) @ wi_l.unsqueeze(-1)).squeeze(-1)
            pdf_l = env.pdf(d.reshape(-1, 3)).view(Q, self.n_brdf) if self.n_light else torch.zeros_like(pdf_b)
            w = _power_heuristic(pdf_b, pdf_l) / pdf_b.clamp_min(1e-30) / self.n_brdf
            w = torch.where(pdf_b > 0, w, torch.zeros_like(w))
            dirs.append((d, wi_l)); weights.append(w)

        d = torch.cat([x[0] for x in dirs], 1)      # (Q, K, 3) world
        wi_l = torch.cat([x[1] for x in dirs], 1)   # (Q, K, 3) local
        w = torch.cat(weights, 1)                    # (Q, K) MIS weight / pdf / count
        K = d.shape[1]
        f = mat.eval(wi_l, wo_l.unsqueeze(1).expand_as(wi_l))           # (Q, K, 3), no cosine
        cos = wi_l[..., 2].clamp_min(0.0)
        contrib = f * (cos * w).unsqueeze(-1)
        live = (contrib.amax(-1) > 0)
        if live_count is not None:
            live_count[0] += int(live.sum())
        L = torch.zeros_like(contrib)
        if live.any():
            dl = d[live]
            side = torch.sign((ng.unsqueeze(1).expand(Q, K, 3)[live] * dl).sum(-1, keepdim=True))
            o = p.unsqueeze(1).expand(Q, K, 3)[live] + side * ng.unsqueeze(1).expand(Q, K, 3)[live] * eps
            blocked = vis.occluded(o, dl)
            Ld = env.radiance(dl)
            L[live] = torch.where(blocked[:, None], torch.zeros_like(Ld), Ld)
        return (contrib * L).sum(1)

    # -- accounting ---------------------------------------------------------------------------
    # Flops of the estimator by term (multiply-add = 2; see frame_cost). Per shaded sample: ω_o to
    # local, the frame, the geometric normal (edges + cross), its normalisation and side.
    FLOPS_PER_SAMPLE = 2 * 9 + 12 + 15 + 6 + 5
    # Per ray: its direction between world and shading frame, MIS weight / pdf, ρ (at least the
    # diffuse term), f·cos·w.
    FLOPS_PER_RAY = 2 * 9 + 6 + 3 + 4
    # Per live ray: the shadow-ray origin, the env map's rotation, the bilinear radiance, Σ contribution·L.
    FLOPS_PER_LIVE_RAY = 2 * 3 + 2 * 9 + 2 * 12 + 2 * 3

    def frame_cost(self, frame_kind: str, num_samples: int, *, pixels: int | None = None) -> FrameCost | None:
        """Compulsory work of one frame of the estimator (``methods.base.FrameCost``): the oracle
        keeps nothing between frames, so every kind costs the same, plus the skinning of a posed
        frame ("P" in the kind, articulated scenes). Multiply-add = 2 flops; transcendentals
        (sin, cos, acos, atan2, pow, sqrt) and the CDF searches are not counted.
        rays: the live shadow rays (those with a non-zero contribution: the only ones the estimate
        needs traced; the oracle traces exactly these), whose traversal — most of a frame — neither
        bytes nor flops bound: ``FrameCost.rays``' roof is the ray rate the machine's fastest tracer
        reaches on the same scene from the same G-buffer points (session 38).

        bytes: per hit sample its position, normal and ω_o (3 × 3 float32), face and region (int64)
        and hit flag (1 B), per missed sample the hit flag, the (H, W, 3) float32 image (``pixels``); the faces hit
        (3 int64) and their distinct vertices (3 float32) for the geometric normals; of the env map, the
        texels the radiance look-ups touch (4 per live ray, at most H·W float32 RGB) and the
        sampling tables a light sample reads (⌈log₂ C⌉ CDF entries by binary search and one cell
        probability, C = (H − 1)·W cells, float64, at most C each).
        flops: per shaded sample ``FLOPS_PER_SAMPLE``, per ray (``light_samples + brdf_samples`` per
        shaded sample) ``FLOPS_PER_RAY``, per live ray (non-zero contribution: traced and looked
        up) ``FLOPS_PER_LIVE_RAY``. "P": per skinned vertex the blended matrix (12 MACs per joint)
        applied to its position and normal (21 MACs), reading position, normal and its weights.

        Hit samples, live rays and faces come from the last `render` on a G-buffer of
        ``num_samples`` samples; without one every sample is a hit, every ray live and every face
        hit (an upper bound of those terms). None before `precompute`.
        """
        if frame_kind not in KINDS:
            raise ValueError(f"frame_kind must be one of {KINDS}, got {frame_kind!r}")
        if isinstance(num_samples, bool) or not isinstance(num_samples, int) or num_samples < 0:
            raise ValueError(f"num_samples must be an int >= 0, got {num_samples!r}")
        if self.scene is None:
            return None
        P, rays = num_samples, self.n_light + self.n_brdf
        if self._last is not None and self._last[0] == P:
            _, Q, live, faces, verts, (H, W) = self._last
        else:
            geom = self.scene.geometry()
            Q, live, faces, verts = P, P * rays, int(geom.F.shape[0]), int(geom.V.shape[0])
            H, W = (int(x) for x in self.scene.envmap.data.shape[:2])
        C = (H - 1) * W
        b = Q * (9 * 4 + 8 + 8 + GBUFFER_HIT_BYTES) + (P - Q) * GBUFFER_HIT_BYTES + output_bytes(P, pixels) + faces * 3 * 8 + verts * 3 * 4
        b += min(H * W, 4 * live) * 3 * 4
        b += min(C, Q * self.n_light * math.ceil(math.log2(max(C, 2)))) * 8 + min(C, Q * self.n_light) * 8
        f = Q * self.FLOPS_PER_SAMPLE + Q * rays * self.FLOPS_PER_RAY + live * self.FLOPS_PER_LIVE_RAY
        if "P" in frame_kind and self.scene.skin_weights:
            for w in self.scene.skin_weights.values():
                nv, J = int(w.shape[0]), int(w.shape[1])
                b += nv * (6 + J) * 4
                f += nv * 2 * (12 * J + 21)
        return FrameCost(int(b), int(f), int(live))
