"""The PTT fast run-time path (``methods.ptt.fast``) against the reference path it replaced
(`PTT._render_reference`, the per-stage code kept as the oracle), and the cost model
(`PTT.frame_cost` / `cost_terms`) against a hand count from the arrays' shapes.

Tiny precompute settings (4 rays, 6×4×4 cube, K = 4, order-2 SH): this is about the run-time
arithmetic, not accuracy, so every library scene stays within a few seconds.
"""
from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from methods.base import GBUFFER_BYTES_PER_SAMPLE, FrameCost, tensor_bytes
from methods.core import sh as _sh
from methods.ptt.method import PTT
from references.gbuffer import make_gbuffer
from scenes.library import SCENES, get_scene
from scenes.sequences import make_sequence

TINY = dict(rays=4, cube_res=4, n_wi=4, brdf_grid=8, brdf_table=8, light_res_1=2, light_res_2=1, n_L=16,
            lobe_fit_samples=256, lobe_vis_samples=128, lobe_vis_res=4, env_res=4, lobe_theta=4, sh_order=2)
# Per scene: which run-time branches it exercises besides the default (2 bounces, lobes, dense T¹).
VARIANTS = {"sphere_plane": {}, "chess": dict(sh_order=3), "alcove": dict(separate=False),
            "shadow_detail": dict(bounces=1), "creature": dict(bounces=0),
            "bunny": dict(compress=dict(clusters=1, eigenvectors=4, light_dim=6)),
            "dragon": dict(brdf_table=3),  # a view table smaller than the window
            "character": {}}
KINDS = ("V", "VB", "VBL", "L", "E")


@pytest.mark.parametrize("shading", ["vertex", "pixel"])
@pytest.mark.parametrize("name", SCENES)
def test_fast_path_equals_reference(name, shading, small):
    """Every library scene PTT accepts, both view stages, V / VB / VBL / L / E sequences rendered in
    order (so the caches of both paths are exercised): the fast image equals the reference to
    float32 round-off."""
    scene = get_scene(name, "test")
    if PTT.capabilities.why_not(scene, "VBL", 0) is not None:
        pytest.skip(PTT.capabilities.why_not(scene, "VBL", 0))
    m = PTT(**{**TINY, **VARIANTS[name]}, shading=shading)
    m.precompute(scene)
    kinds = KINDS if name in ("chess", "alcove") else ("V", "VB", "VBL")
    for kind in kinds:
        for frame in make_sequence(scene, kind, n_frames=2, seed=3):
            frame = small(frame)
            gb = make_gbuffer(scene, frame, 1)
            fast, ref = m.render(frame, gb), m._render_reference(frame, gb)
            scale = float(ref.abs().max())
            assert scale > 0
            torch.testing.assert_close(fast, ref, rtol=1e-5, atol=2e-6 * max(scale, 1.0),
                                       msg=lambda s: f"{name} {kind} frame {frame.index}: {s}")


@pytest.mark.parametrize("native", [True, False])
@pytest.mark.parametrize("R,P,K,T", [(3, 4, 16, 8), (2, 3, 4, 5), (1, 1, 2, 3)])
def test_region_tables_are_the_products_summed_in_order(R, P, K, T, native, monkeypatch):
    """`fast.region_tables`' W_r (lane-wise products per p over `view_table_rows`; the native loop
    ``native.region_rows`` or the eager passes) is, bit for bit,
    the float32 sum Σ_p W(p, k, texel) H(r, p, c) taken in p order without FMA (what MKL's batched
    (T²·K, P) @ (P, 3) products gave: the chess and creature bench tables were equal), and the exact
    float64 product to float32 round-off; a_r is the einsum's."""
    from methods.ptt import fast as _fast
    from methods.ptt import native as _native

    if native and not _native.available():
        pytest.skip("no C compiler")
    monkeypatch.setattr(_fast, "USE_NATIVE", native)
    if native:
        assert _native.region_rows(_fast.view_table_rows(torch.zeros(P * K, T, T), K), torch.zeros(P, R, 1, K * 3)) \
            is not None

    g = torch.Generator().manual_seed(R * 100 + P)
    W_tab = torch.randn(P * K, T, T, generator=g)
    H = torch.rand(R, P, 3, generator=g)
    H[0, -1] = 0.0  # a basis function a material does not use
    lobe_a = torch.rand(P, 5, 2, generator=g)
    Wr, ar = _fast.region_tables(H, W_tab, K, lobe_a)
    assert Wr.shape == (R * T * T, K * 3) and Wr.is_contiguous()
    W = W_tab.reshape(P, K, T, T)
    want = None
    for p in range(P):  # (r, y, x, k, c)
        t = W[p][None, :, :, :, None].permute(0, 2, 3, 1, 4) * H[:, p][:, None, None, None, :]
        want = t if want is None else want + t
    assert torch.equal(Wr, want.reshape(R * T * T, K * 3))
    exact = torch.einsum("pkyx,rpc->ryxkc", W.double(), H.double()).reshape(R * T * T, K * 3)
    assert float((Wr.double() - exact).abs().max()) <= 4 * P * 6e-8 * float(exact.abs().max())
    Wr2, _ = _fast.region_tables(H, W_tab, K, None, _fast.view_table_rows(W_tab, K))
    assert torch.equal(Wr2, Wr)
    assert torch.equal(ar, torch.einsum("rpc,pnl->rnlc", H, lobe_a).reshape(R * 5, 2 * 3))


@pytest.mark.parametrize("R,P,K,T", [(3, 4, 16, 48), (2, 2, 16, 48), (1, 4, 8, 16), (1, 3, 4, 5), (4, 5, 4, 8),
                                     (2, 1, 2, 3)])
def test_native_region_tables_are_the_eager_tables_bit_for_bit(R, P, K, T, monkeypatch):
    """``native.region_tables`` (session 40: W_r's rows over nt threads, the lanes read from H, written
    into the previous frame's W_r) equals ``native.region_rows`` (and so the eager passes, above) bit for
    bit, at 1–3 threads, into fresh and reused tables; a_r is untouched (the einsum)."""
    from methods.ptt import fast as _fast
    from methods.ptt import native as _native

    if not _native.available():
        pytest.skip("no C compiler")
    g = torch.Generator().manual_seed(R * 1000 + P * 10 + K)
    W_tab = torch.randn(P * K, T, T, generator=g)
    W_rows = _fast.view_table_rows(W_tab, K)
    lobe_a = torch.randn(P, 7, 3, generator=g)
    prev = None
    for step in range(3):
        H = torch.randn(R, P, 3, generator=g)
        monkeypatch.setattr(_fast, "NATIVE_TABLES", False)
        want = _fast.region_tables(H, W_tab, K, lobe_a, W_rows)
        monkeypatch.setattr(_fast, "NATIVE_TABLES", True)
        for nt in (1, 2, 3):
            got = _fast.region_tables(H, W_tab, K, lobe_a, W_rows, nt=nt, out=prev)
            if prev is not None:  # written in place
                assert got[0].data_ptr() == prev[0].data_ptr()
            assert torch.equal(got[0], want[0]), (step, nt)
            assert torch.equal(got[1], want[1]), (step, nt)
            prev = got
        assert torch.equal(_native.region_tables(W_rows, H, 2), want[0])
    other = torch.empty(1, 3)  # a table of another shape is not written into
    got = _native.region_tables(W_rows, H, 2, other)
    assert got.data_ptr() != other.data_ptr() and got.shape == (R * T * T, K * 3)


def test_world_frame_sh_equals_local_evaluation():
    """The lobes' SH term is evaluated in the world frame: Σ_s I1w(s) Y_s(R) = Σ_s I1(s) Y_s(F R)
    for the rotation built per vertex (``fast.build_static``)."""
    from methods.ptt.fast import build_static

    g = torch.Generator().manual_seed(0)
    N = torch.nn.functional.normalize(torch.randn(50, 3, generator=g), dim=-1)
    F = torch.tensor([[0, 1, 2]])
    st = build_static(torch.randn(50, 3, generator=g), N, F, torch.zeros(1, dtype=torch.int64), 1, 4)
    I1 = torch.randn(50, 16, 3, generator=g)
    R = torch.nn.functional.normalize(torch.randn(50, 3, generator=g), dim=-1)
    local = torch.einsum("vab,vb->va", st.frames, R)
    ref = (I1 * _sh.sh_eval(local, 4)[..., None]).sum(1)
    got = (torch.bmm(st.sh_rot, I1) * _sh.sh_eval(R, 4)[..., None]).sum(1)
    torch.testing.assert_close(got, ref, rtol=1e-5, atol=1e-5)


@pytest.fixture(scope="module", params=["vertex", "pixel"])
def tiny(request, small):
    scene = get_scene("sphere_plane", "test")
    m = PTT(**TINY, shading=request.param)
    m.precompute(scene)
    frame = small(make_sequence(scene, "V", n_frames=1, seed=0)[0], 24)
    gb = make_gbuffer(scene, frame, 1)
    return m, frame, gb


def _referenced_texels(m, gb, hit, cam_origin):
    """Hand count of the view tables' texels a shading="vertex" frame reads: per referenced
    (vertex, region) pair the bilinear cell of ωo_x in the W_r table (per region and across
    regions) and the two θo nodes of the lobe table; per hit sample the bilinear cell of R in
    the env grid. Built from the reference's functions (to_local, table_coords, reflect)."""
    from methods.core.frames import reflect, to_local
    from methods.ptt import specular as spec
    from methods.ptt.transport import table_coords

    R_, T, nt = len(m.regions), m.factors.W_tab.shape[-1], m.lobe_table.theta.shape[0]
    faces = gb.face[hit]
    key = torch.unique(m.F[faces] * R_ + gb.region[hit][:, None])
    v, r = key // R_, key % R_
    cam = torch.tensor(cam_origin, dtype=torch.float32)
    wo = torch.nn.functional.normalize(cam - m.V[v], dim=-1)
    loc = to_local(wo, m.N[v])
    x = ((table_coords(loc) + 1.0) * (T / 2.0) - 0.5).clamp(0.0, T - 1.0)
    i = x.floor().long().clamp(max=T - 2)
    cells = [(i[:, 1] + dy) * T + i[:, 0] + dx for dy in (0, 1) for dx in (0, 1)]
    texW = torch.unique(torch.cat([r * T * T + c for c in cells])).numel()
    tex = torch.unique(torch.cat(cells)).numel()
    th = torch.acos(loc[:, 2].clamp(-1, 1))
    i0 = (th / (math.pi / 2) * nt - 0.5).clamp(0.0, nt - 1.0).floor().long().clamp(max=nt - 2)
    nodes = torch.cat([i0, i0 + 1])
    rows_a, n_a = torch.unique(torch.cat([r * nt + i0, r * nt + i0 + 1])).numel(), torch.unique(nodes).numel()
    n = torch.nn.functional.normalize(gb.normal[hit], dim=-1)
    Rq = torch.nn.functional.normalize(reflect(gb.wo[hit], n), dim=-1)
    env = m._f_env
    idx, _ = spec.latlong_cells(Rq.T.contiguous(), env.to_world, env.height, env.width)
    return texW, tex, rows_a, n_a, torch.unique(idx).numel()


def test_frame_cost_is_the_hand_count(tiny):
    """flops and bytes of every frame kind re-derived here from the arrays' shapes."""
    m, frame, gb = tiny
    assert m.frame_cost("V", gb.num_samples) is not None
    m.render(frame, gb)
    vertex = m.config["shading"] == "vertex"
    nv = m.V.shape[0]
    R, P, K = len(m.regions), m.factors.n_P, m.factors.K
    S, order, L = m.C.shape[0], 2, len(m.config["lobe_degrees"])
    T, nt = m.factors.W_tab.shape[-1], m.lobe_table.theta.shape[0]
    hit = torch.nonzero(gb.hit).squeeze(-1)
    Q, P_all = hit.numel(), gb.num_samples
    faces = gb.face[hit]
    verts = torch.unique(m.F[faces]).numel()
    pairs = torch.unique(m.F[faces] * R + gb.region[hit][:, None]).numel()
    H, W = m._f_env.height, m._f_env.width
    nnz = sum(f.kernel.values().numel() for f in m.env_filters if f is not None)
    n_filt = sum(f is not None for f in m.env_filters)
    if vertex:
        texW, tex, rows_a, n_a, tex_env = _referenced_texels(m, gb, hit, frame.camera.origin)
        C = 3 + 3 * L + 3
        # per pair: ωo (12), glossy bilinear + dot (5·K·3), a_k (2L·3), V_c (4L), s (3L), SH term;
        # per sample: interpolation (3·C), R (6), E^(k) bilinear (4L·3), Σ_k s E (3L)
        view = 2 * pairs * (12 + 5 * K * 3) + 2 * Q * 3 * C + 2 * pairs * (6 * L + 4 * L + 3 * L) \
            + 2 * Q * (6 + 12 * L + 3 * L) + 2 * pairs * (3 * S + 3 * L * order + 3 * L + 3)
        brdf = 2 * nv * (R * P * S * 3 + S * K * 3) + 2 * nv * ((R * P) ** 2 * 3 + 3 * K) + (R * P) ** 2 * 3 \
            + 2 * nv * K * 3
        tables = 2 * texW * K * P * 3 + 2 * rows_a * L * P * 3
    else:
        blocks = 1 + 9  # Σ_b (2b+1)² for order 2
        # view stage: glossy (X on >= 4 texels per pair, 12 corners·3 per sample, 27 frame MACs),
        # lobes (frames 27, a_k 2L·3, E^(k) 4L·3, V_c 12L, E·V_c + Li·cos 2L·3, Σ_k L·3), SH term
        view = 2 * (pairs * 4 * K * 3 + Q * (36 + 27)) + 2 * Q * (27 + 6 * L + 12 * L + 12 * L + 6 * L + 3 * L) \
            + 2 * Q * (9 * S + 3 * S + 3 * L * order)
        brdf = 2 * nv * (R * P * S * 3 + S * K * 3) + 2 * nv * ((R * P) ** 2 * 3 + 3 * K) + (R * P) ** 2 * 3 \
            + 2 * nv * K * 3 + 2 * nv * blocks * 3
        tables = 2 * R * T * T * K * P * 3 + 2 * R * nt * L * P * 3
    L1, L2 = 6 * 2 ** 2, 6 * 1 ** 2  # light_res_1 = 2, light_res_2 = 1
    light = 2 * nv * K * 16 * 3 + 2 * 3 * nv * R * P * S * L1 + 2 * 3 * nv * L2 * (R * P) ** 2 + 2 * 3 * nnz \
        + 2 * n_filt * H * W * 12
    assert m.frame_cost("V", P_all).flops == view
    assert m.frame_cost("VB", P_all).flops == view + brdf + tables
    assert m.frame_cost("VBL", P_all).flops == view + brdf + tables + light
    assert m.frame_cost("L", P_all).flops == m.frame_cost("E", P_all).flops == view + brdf + light
    # bytes: G-buffer + output + referenced rows (V); a rebuilt cache counts its whole write
    f4 = 4
    if vertex:  # face, barycentrics, hit word, normal and ωo; face_pairs rows; positions + normals
        v_bytes = Q * 41 + (P_all - Q) * 1 + P_all * 12 + torch.unique(faces).numel() * 24 + verts * 24 \
            + verts * K * 12 + texW * K * 12 + min(verts * 16 * L, tensor_bytes(m.lobe_vis)) + rows_a * L * 12 \
            + L * tex_env * 12 + verts * S * 12
    else:
        gbuf = Q * (GBUFFER_BYTES_PER_SAMPLE + 8) + (P_all - Q) * 1 + P_all * 12
        v_bytes = gbuf + torch.unique(faces).numel() * 24 + verts * 12 + verts * K * 12 + R * T * T * K * 12 \
            + min(verts * 16 * L, tensor_bytes(m.lobe_vis)) + R * nt * L * 12 + L * min(H * W, Q * 4) * 12 \
            + verts * S * 12
    assert m.frame_cost("V", P_all).bytes == v_bytes
    vb = m.cost_terms("VB", P_all)[0]
    assert vb["E"] == nv * K * 12 and vb["T1L"] == nv * R * P * S * 12 and vb["T2L"] == nv * (R * P) ** 2 * 12
    assert vb["W_tables"] == (tex if vertex else T * T) * P * K * f4
    assert vb["lobe_weights"] == (n_a if vertex else nt) * P * L * f4
    assert ("sh_rotation" in vb) == (not vertex)
    vbl = m.cost_terms("VBL", P_all)[0]
    assert vbl["T1"] == tensor_bytes(m.T1) and vbl["T2"] == tensor_bytes(m.T2)
    assert vbl["direct_transport"] == tensor_bytes(m.dt.idx, m.dt.val)
    assert vbl["lobe_maps"] == n_filt * H * W * 12


def test_frame_cost_without_bounces_counts_e_once(tiny):
    """bounces = 0 (the perf suite's direct cells): E = E⁰, so a BRDF change neither reads E⁰ nor
    rewrites E — a VB frame reads what V reads plus the per-region tables it rebuilds — and a
    lighting change writes E once (no E⁰ read on top, no E = E⁰ + … additions). Session 35: the count
    had E⁰ plus a full E write in VB (3.3 MB of chess VB's 24.4 MB)."""
    m0, frame, gb = tiny
    m = m0.with_bounces(0)
    m.render(frame, gb)
    P_all, nv, K = gb.num_samples, m.V.shape[0], m.factors.K
    v, vb, ll = (m.cost_terms(k, P_all) for k in ("V", "VB", "L"))
    assert "E0" not in vb[0] and "E0" not in ll[0] and "brdf_E" not in vb[1] and "brdf_E" not in ll[1]
    assert vb[0]["E"] == v[0]["E"] < nv * K * 12  # the referenced rows only
    extra = {k: b for k, b in vb[0].items() if k not in v[0] or v[0][k] != b}
    assert set(extra) == {"W_tables", "lobe_weights"} | ({"sh_rotation"} if "sh_rotation" in vb[0] else set())
    assert ll[0]["E"] == nv * K * 12
    # with bounces the BRDF stage does rebuild E from E⁰ (Sun eq. 4)
    vb2 = m0.cost_terms("VB", P_all)
    assert vb2[0]["E0"] == vb2[0]["E"] == nv * K * 12 and vb2[1]["brdf_E"] == 2 * nv * K * 3


def test_frame_cost_bytes_bounded_by_the_arrays_read(tiny):
    """No padding: a frame's bytes never exceed G-buffer + output + every run-time array and cache."""
    m, frame, gb = tiny
    m.render(frame, gb)
    E0, T1L, T2L, (Ek, stack) = m._f_light
    caches = tensor_bytes(E0, T1L, T2L, *m._f_tabs, *[t for t in m._f_E if t is not None], *[e.data for e in Ek],
                          stack.ext)
    everything = sum(m.memory().values()) + caches + tensor_bytes(m.scene.envmap.data) \
        + gb.num_samples * (GBUFFER_BYTES_PER_SAMPLE + 8 + 12)
    costs = [m.frame_cost(k, gb.num_samples) for k in KINDS]
    assert all(isinstance(c, FrameCost) for c in costs)
    assert all(0 < c.bytes <= everything for c in costs)
    v, vb, vbl = costs[:3]
    assert v.bytes < vb.bytes < vbl.bytes and v.flops < vb.flops < vbl.flops


def test_frame_cost_validates_and_needs_precompute():
    assert PTT().frame_cost("V", 10) is None
    for kind, n in (("X", 10), ("P", 10), ("V", -1), ("V", 1.5)):
        with pytest.raises(ValueError):
            PTT().frame_cost(kind, n)


@pytest.mark.parametrize("n_samples", [1, 1000, (1 << 15) + 7])
def test_fused_sample_stage_equals_eager(n_samples, monkeypatch):
    """shading="vertex": the per-sample stage as compiled loops (`fast.shade_samples_fused`:
    `mirror_uv`, `shade_block` with S2 = 1, static blocks) equals the eager `fast.shade_samples` to
    float32 round-off, with and without the one-bounce column, with the rows as `vertex_view` gives
    them to the fused path (`fast.padded` to `table_width`, C passed), including a last block shorter
    than the others (blocks capped at 2¹² here, so 2¹⁵ + 7 samples take nine)."""
    from methods.ptt import fast as F

    monkeypatch.setattr(F, "MAX_SAMPLE_BLOCK", 1 << 12)

    g, n_pairs, L, face_pairs, face, bary, normal, wo, env = _random_shading_inputs(n_samples, 0)
    for C in (3 + 3 * L, 6 + 3 * L):
        table = torch.randn(n_pairs + 1, C, generator=g)
        ref = F.shade_samples(face_pairs, table, face, bary, normal, wo, env, L)
        out = F.shade_samples_fused(face_pairs, table, face, bary, normal, wo, env, L)
        torch.testing.assert_close(out, ref, rtol=1e-5, atol=1e-5 * float(ref.abs().max()))
        wide = F.padded(table, F.table_width(C))
        out = F.shade_samples_fused(face_pairs, wide, face, bary, normal, wo, env, L, C)
        torch.testing.assert_close(out, ref, rtol=1e-5, atol=1e-5 * float(ref.abs().max()))


@pytest.mark.parametrize("S2,n_pixels", [(1, 1000), (4, 1 << 10), (4, (1 << 13) + 5)])
def test_fused_pixel_stage_equals_eager(S2, n_pixels, monkeypatch):
    """`fast.shade_pixels_fused` (samples shaded and box-filtered per static block, `shade_block`)
    equals the eager `fast.shade_samples` + `fast.box_filter` to float32 round-off, including a last
    block shorter than the others (blocks capped at 2¹² here) and a frame of exactly one full block
    (2¹⁰ pixels × 4: the block's result returned as the image); it declines (None) when a block
    cannot hold whole pixels."""
    from methods.ptt import fast as F

    monkeypatch.setattr(F, "MAX_SAMPLE_BLOCK", 1 << 12)

    g, n_pairs, L, face_pairs, face, bary, normal, wo, env = _random_shading_inputs(S2 * n_pixels, 1)
    for C in (3 + 3 * L, 6 + 3 * L):
        table = torch.randn(n_pairs + 1, C, generator=g)
        ref = F.box_filter(F.shade_samples(face_pairs, table, face, bary, normal, wo, env, L), n_pixels, 1, S2)
        out = F.shade_pixels_fused(face_pairs, table, face, bary, normal, wo, env, L, S2)
        torch.testing.assert_close(out.view(n_pixels, 1, 3), ref, rtol=1e-5, atol=1e-5 * float(ref.abs().max()))
    assert F.shade_pixels_fused(face_pairs, table, face[:9], bary[:9], normal[:9], wo[:9], env, L, 9) is None



def _shade_block_masked(face, bary, r, fx, fy, face_pairs, table, env, lanes, W, S2):
    """`fast._shade_block` as it was before session 23 (the oracle of the ``where`` / ``embedding``
    form): t = max(0, a)·[B lanes] + a·e + a·[u lanes] per lane, rows read as ``table[idx]``."""
    n = face.shape[0]
    P = n // S2
    width = table.shape[1]
    fv, b1v, b2v = face.view(P, S2), bary[:, 0].view(P, S2), bary[:, 1].view(P, S2)
    rv, fxv, fyv = r.view(P, S2), fx.view(P, S2), fy.view(P, S2)
    t = None
    for j in range(S2):
        f = fv[:, j]
        p0, p1, p2 = face_pairs[f, 0], face_pairs[f, 1], face_pairs[f, 2]
        b1, b2 = b1v[:, j], b2v[:, j]
        b0 = 1.0 - b1 - b2
        fx_, fy_ = fxv[:, j], fyv[:, j]
        gx, gy = 1.0 - fx_, 1.0 - fy_
        rj = rv[:, j].to(torch.int64)
        a = table[p0] * b0[:, None] + table[p1] * b1[:, None] + table[p2] * b2[:, None]
        e = (env[rj] * (gx * gy)[:, None] + env[rj + 1] * (fx_ * gy)[:, None]
             + env[rj + (W + 1)] * (gx * fy_)[:, None] + env[rj + (W + 2)] * (fx_ * fy_)[:, None])
        tj = a.clamp_min(0.0) * lanes[0, :width] + a * e + a * lanes[1, :width]
        t = tj if t is None else t + tj
    out = torch.stack([(t * lanes[2 + c, :width]).sum(-1) for c in range(3)], -1)
    return out * (1.0 / S2)


@pytest.mark.parametrize("S2", [1, 4])
def test_shade_block_equals_the_masked_lane_form_bit_for_bit(S2):
    """`fast._shade_block` (lanes chosen with ``where``, rows read with ``embedding``) gives the same
    bits as the masked-lane form it replaced (`_shade_block_masked`), eagerly: with and without the
    one-bounce u column, negative Gouraud sums (the B clamp), misses (face −1, the zero face of
    `fast.miss_face_pairs`) and env rows built by `fast.env_stack` (0 on the B and u lanes). The
    compiled kernel is compared with the eager reference path by the tests above."""
    from methods.ptt import fast as F

    n = S2 * 3001
    g, n_pairs, L, face_pairs, face, bary, normal, wo, _ = _random_shading_inputs(n, 2)
    face = torch.where(torch.rand(n, generator=g) < 0.05, -1, face)
    fpm = torch.cat([face_pairs, torch.full((1, 3), n_pairs, dtype=face_pairs.dtype)])
    H, W = 16, 32
    maps = [_FakeEnv(torch.rand(H, W, 3, generator=g) * 4.0) for _ in range(L)]
    for C in (3 + 3 * L, 6 + 3 * L):
        width, erows, table, lanes, r, fx, fy = _shade_tables(g, maps, C, L, n_pairs, H, W, n)
        new = F._shade_block(face, bary, r, fx, fy, fpm, table, erows, lanes, W, S2)
        old = _shade_block_masked(face, bary, r, fx, fy, fpm, table, erows, lanes, W, S2)
        assert torch.equal(new, old)
        assert bool((new.abs() > 0).any())


@dataclasses.dataclass
class _FakeEnv:
    """What `fast.env_stack` reads of an ``EnvMap``: data (H, W, 3) and to_world."""

    data: torch.Tensor
    to_world: torch.Tensor = dataclasses.field(default_factory=lambda: torch.eye(3))

def _shade_tables(g, maps: list, C: int, L: int, n_pairs: int, H: int, W: int, n: int) -> tuple:
    """A shading stage's tables for C columns and L env maps (``fast.env_stack`` rows, a random pair
    table whose last row — the miss face's — is 0, the lane masks) and n random env cells:
    (width, erows, table, lanes, r, fx, fy)."""
    from methods.ptt import fast as F

    width = F.table_width(C)
    erows = F.env_rows(F.env_stack(maps, width), width)
    table = F.padded(torch.randn(n_pairs + 1, C, generator=g), width)
    table[-1] = 0.0
    lanes = F._lane_masks(C, L, width)
    r = torch.randint(0, (H - 1) * (W + 1) - 1, (n,), generator=g, dtype=torch.int32)
    fx, fy = torch.rand(n, generator=g), torch.rand(n, generator=g)
    return width, erows, table, lanes, r, fx, fy


def _random_shading_inputs(n: int, seed: int):
    """Random inputs of `fast.shade_samples` for n samples: (generator, n_pairs, L, face_pairs, face,
    bary, normal, wo, env); 4 lobes, 300 vertex/region pairs, a 16 × 32 env stack."""
    from methods.ptt import fast as F

    g = torch.Generator().manual_seed(seed)
    n_pairs, L, H, W = 300, 4, 16, 32
    face_pairs = torch.randint(0, n_pairs + 1, (500, 3), generator=g)
    face = torch.randint(0, 500, (n,), generator=g)
    bary = torch.rand(n, 2, generator=g) * 0.5
    normal = torch.randn(n, 3, generator=g)
    wo = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1)
    to_world = torch.linalg.qr(torch.randn(3, 3, generator=g))[0].contiguous()
    env = F.EnvStack(torch.rand(H * (W + 1), 3 * L, generator=g), to_world, H, W)
    return g, n_pairs, L, face_pairs, face, bary, normal, wo, env


def test_mirror_uv_is_the_eager_formula_to_round_off():
    """`fast.mirror_uv` — the ONE compiled formula that both the fast path and the reference
    (`PTT._shade_vertex`) read the prefiltered maps with (its docstring: a compiled acos / atan2
    differs from the eager one in the last bit, which flips lat-long cells at their boundaries) —
    against the eager `specular.mirror_dirs` + `specular._latlong_uv`: (u, v) to a few ulps of the
    direction (scaled by the conditioning of atan2 / acos near the poles, 1/ρ with ρ the direction's
    distance from the map's axis), and the same bilinear cells wherever the eager coordinate is not
    within that tolerance of a cell boundary."""
    from methods.ptt import fast as F
    from methods.ptt import specular as spec

    g = torch.Generator().manual_seed(5)
    n = 40_000 + 3  # several static blocks and a padded last one
    normal = torch.randn(n, 3, generator=g) * (0.5 + torch.rand(n, 1, generator=g))  # not unit
    wo = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1)
    to_world = torch.linalg.qr(torch.randn(3, 3, generator=g, dtype=torch.float64))[0].float().contiguous()
    u, v = F.mirror_uv(normal, wo, to_world)
    R = spec.mirror_dirs(normal, wo)
    ue, ve = spec._latlong_uv(R, to_world)
    ly = (to_world.T @ R)[1]
    rho = (1.0 - ly.double() ** 2).clamp_min(0.0).sqrt().float().clamp_min(1e-4)
    tol = 16 * torch.finfo(torch.float32).eps / rho
    du = torch.remainder(u - ue + 0.5, 1.0) - 0.5  # u wraps at ±1/2
    assert bool((du.abs() <= tol).all()) and bool(((v - ve).abs() <= tol).all())
    H, W = 32, 64
    idx, _ = spec._uv_cells(u, v, H, W)
    idx_e, _ = spec._uv_cells(ue, ve, H, W)
    x = torch.remainder(ue - 0.5 / W, 1.0) * W
    y = ve * (H - 1)
    far = ((x - x.round()).abs() > W * tol) & ((y - y.round()).abs() > H * tol)
    assert far.float().mean() > 0.95
    assert torch.equal(idx[far], idx_e[far])


def _ulps(got: torch.Tensor, want64: torch.Tensor) -> torch.Tensor:
    """|got − want64| in float32 ulps of the float64 value (the spacing above its float32 rounding)."""
    w = want64.abs().float()
    return (got.double() - want64).abs() / (torch.nextafter(w, torch.full_like(w, math.inf)) - w).double()


def test_lat_long_polynomials_are_within_a_few_ulps():
    """`fast.acos_poly` / `fast.atan2_poly` (the mirror look-up's lat-long angles, session 39: float32
    polynomials instead of torch.acos / torch.atan2, so that the compiled kernel, the eager form and
    the native cells share one formula bit for bit) are as accurate as the float32 library calls:
    acos within 1.5 ulps of the float64 acos of the float32 input over every 64th float32 of [−1, 1]
    (torch.acos: 0.79; the polynomial measured 1.35), atan2 within 3 ulps and 2.7e-7 rad over 2^21
    (y, x) of magnitudes 1e-9..1e9 and the axes, octant diagonals and the tan π/8 reduction boundary
    (torch.atan2: 1.48 ulps, 2.5e-7 rad; the polynomial measured 2.9 ulps, 2.6e-7 rad) — and their
    special values: acos(±1), acos(0), atan2 on the axes."""
    from methods.ptt import fast as F

    y = torch.arange(0, 0x3F800001, 64, dtype=torch.int64).to(torch.int32).view(torch.float32)
    for c in torch.cat([y, -y]).split(1 << 21):
        assert float(_ulps(F.acos_poly(c), torch.acos(c.double())).max()) <= 1.5
    ends = torch.tensor([1.0, -1.0, 0.0, -0.0, 0.5, -0.5])
    assert torch.equal(F.acos_poly(ends), torch.tensor([0.0, math.pi, math.pi / 2, math.pi / 2, math.pi / 3,
                                                        2 * math.pi / 3]))
    g = torch.Generator().manual_seed(17)
    n = 1 << 21
    d = torch.randn(n, 2, generator=g, dtype=torch.float64) * torch.exp(torch.randn(n, 1, generator=g,
                                                                                     dtype=torch.float64) * 7)
    d = d.clamp(-1e9, 1e9).float()
    t8 = math.tan(math.pi / 8)
    m = torch.rand(4096, generator=g) + 0.5
    special = [(m, m), (-m, m), (m, -m), (-m, -m), (m * t8, m), (m, m * t8), (-m * t8, -m), (m * 0, m), (m * 0, -m),
               (m, m * 0), (-m, m * 0), (m * t8 * (1 + 1e-7), m), (m * t8 * (1 - 1e-7), -m)]
    yy = torch.cat([d[:, 0]] + [a for a, _ in special])
    xx = torch.cat([d[:, 1]] + [b for _, b in special])
    got, want = F.atan2_poly(yy, xx), torch.atan2(yy.double(), xx.double())
    assert float(_ulps(got, want).max()) <= 3.0
    assert float((got.double() - want).abs().max()) <= 2.7e-7
    axes = F.atan2_poly(torch.tensor([0.0, 0.0, 1.0, -1.0, 0.0]), torch.tensor([1.0, -1.0, 0.0, 0.0, 0.0]))
    assert torch.equal(axes, torch.tensor([0.0, math.pi, math.pi / 2, -math.pi / 2, 0.0]))


def test_mirror_uv_compiled_is_the_eager_formula_bit_for_bit():
    """The compiled `fast.mirror_uv` (what the reference and the fast path read the maps with) equals
    its eager form `fast._mirror_uv` bit for bit (float32 products, sums, one division, correctly
    rounded square roots, compares and selects, no FMA contraction: the same bits in Inductor's
    kernel and in eager torch — which is why acos_poly takes its square root through float64)."""
    from methods.ptt import fast as F

    g = torch.Generator().manual_seed(19)
    n = 40_000 + 3
    normal = torch.randn(n, 3, generator=g) * (0.5 + torch.rand(n, 1, generator=g))
    normal[::997] = torch.tensor([0.0, 1.0, 0.0])
    wo = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1)
    wo[::997] = torch.tensor([0.0, 1.0, 0.0])
    for _ in range(2):
        to_world = torch.linalg.qr(torch.randn(3, 3, generator=g, dtype=torch.float64))[0].float().contiguous()
        u, v = F.mirror_uv(normal, wo, to_world)
        ue, ve = F._mirror_uv(normal, wo, to_world)
        assert torch.equal(u, ue) and torch.equal(v, ve)


def test_mirror_cells_are_the_reference_cells():
    """`fast.mirror_cells_block` (what the compiled sample stage reads: the lat-long cell of the mirror
    direction, computed in the loop that computes it) gives exactly the cell of ``specular._uv_cells``
    at the (u, v) of `fast.mirror_uv` (the reference path's look-up): the same first row and the
    same corner weights, bit for bit, on several grids and rotations."""
    from methods.ptt import fast as F
    from methods.ptt import specular as spec

    g = torch.Generator().manual_seed(7)
    n = 20_000 + 5
    normal = torch.randn(n, 3, generator=g) * (0.5 + torch.rand(n, 1, generator=g))
    wo = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1)
    for H, W in ((256, 512), (32, 64), (33, 70)):
        to_world = torch.linalg.qr(torch.randn(3, 3, generator=g, dtype=torch.float64))[0].float().contiguous()
        u, v = F.mirror_uv(normal, wo, to_world)
        idx, w = spec._uv_cells(u, v, H, W)
        r, fx, fy = F.mirror_cells_block(normal, wo, to_world, H, W)
        assert r.dtype == torch.int32 and torch.equal(r.long(), idx[:, 0])
        gx, gy = 1.0 - fx, 1.0 - fy
        assert torch.equal(torch.stack([gx * gy, fx * gy, gx * fy, fx * fy], -1), w)


def test_mirror_cells_of_a_nan_direction_stay_in_the_table():
    """A NaN shading normal (a degenerate G-buffer sample) gives a NaN mirror direction; its cell in
    `fast.mirror_cells_block` is row 0, so `shade_block`'s four corner rows r, r + 1, r + W + 1, r + W + 2 stay inside the table (no
    out-of-bounds read, its index checks are off) and the other samples' cells are unchanged."""
    from methods.ptt import fast as F
    from methods.ptt import specular as spec

    g = torch.Generator().manual_seed(11)
    n = 4096 + 7
    normal = torch.randn(n, 3, generator=g)
    wo = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1)
    bad = torch.zeros(n, dtype=torch.bool)
    bad[3::101] = True
    normal[bad] = float("nan")
    to_world = torch.eye(3)
    for H, W in ((256, 512), (33, 70)):
        r, fx, fy = F.mirror_cells_block(normal, wo, to_world, H, W)
        assert r.dtype == torch.int32
        assert bool((r[bad] == 0).all())
        assert int(r.min()) >= 0 and int(r.max()) + W + 2 < H * (W + 1)
        idx, _ = spec._uv_cells(*F.mirror_uv(normal[~bad], wo[~bad], to_world), H, W)
        assert torch.equal(r[~bad].long(), idx[:, 0])


def test_misses_take_the_compiled_pixel_stage_without_recompiling(small):
    """A frame with misses after frames without (chess bench V frame 4 had one miss in 262 144
    samples and compiled two more graphs in a timed frame, 0.98 s against 0.05 s): misses (face −1)
    read the zero face of `fast.miss_face_pairs`, so `fast.shade_pixels_fused` shades them as 0 with
    the same static shapes — no new compiled graph — and the image still equals the reference;
    a G-buffer whose misses break the face −1 contract takes the two-pass route (and equals it too)."""
    from torch._dynamo.utils import counters

    from methods.core.fused import compile_enabled

    scene = get_scene("chess", "test")
    m = PTT(**{**TINY, **VARIANTS["chess"]}, bounces=0)
    m.precompute(scene)
    frames = [small(f) for f in make_sequence(scene, "V", n_frames=3, seed=3)]
    gb = make_gbuffer(scene, frames[0], 2)
    j = int(torch.nonzero(gb.hit)[0])
    full = dataclasses.replace(gb, **{k: torch.where(gb.hit.view(-1, *[1] * (getattr(gb, k).dim() - 1)),
                                                     getattr(gb, k), getattr(gb, k)[j])
                                      for k in ("hit", "face", "bary", "normal", "wo", "region")})
    assert bool(full.hit.all())
    miss = torch.zeros_like(full.hit)
    miss[5::97] = True  # misses with the G-buffer's values (references.gbuffer)
    holes = dataclasses.replace(full, hit=~miss, face=torch.where(miss, -1, full.face),
                                bary=torch.where(miss[:, None], 0.0, full.bary),
                                normal=torch.where(miss[:, None], 0.0, full.normal),
                                region=torch.where(miss, -1, full.region))
    m.render(frames[0], full)  # compiles (the warm-up frame)
    for f, g in ((frames[1], holes), (frames[2], full), (frames[2], holes)):
        before = counters["stats"]["unique_graphs"]
        fast = m.render(f, g)
        if compile_enabled():  # the fast path's graphs only (the reference compiles its own mirror_uv)
            assert counters["stats"]["unique_graphs"] == before, f"frame {f.index} compiled"
        ref = m._render_reference(f, g)
        scale = float(ref.abs().max())
        torch.testing.assert_close(fast, ref, rtol=1e-5, atol=2e-6 * max(scale, 1.0))
    # misses that are not face −1: not the zero face, so the two-pass route (same image)
    odd = dataclasses.replace(holes, face=torch.where(miss, 0, full.face))
    torch.testing.assert_close(m.render(frames[2], odd), m._render_reference(frames[2], odd), rtol=1e-5,
                               atol=2e-6 * max(scale, 1.0))


def test_all_true_is_tensor_all():
    """`fast.all_true` (the byte minimum of a bool mask) equals ``bool(mask.all())``: all true, one
    false anywhere (first, last, middle), all false, empty, and a strided view."""
    from methods.ptt import fast as F

    for n in (0, 1, 7, 262_144 + 3):
        m = torch.ones(n, dtype=torch.bool)
        assert F.all_true(m) is True
        for i in {0, n // 2, n - 1} if n else ():
            k = m.clone()
            k[i] = False
            assert F.all_true(k) is False and bool(k.all()) is False
        assert F.all_true(torch.zeros(n, dtype=torch.bool)) is bool(torch.zeros(n, dtype=torch.bool).all())
    g = torch.Generator().manual_seed(3)
    x = torch.rand(1000, 2, generator=g) > 0.001
    for v in (x[:, 0], x[:, 1], x.reshape(-1)):
        assert F.all_true(v) is bool(v.all())


def test_pair_cells_int32_indices_are_the_int64_ones():
    """`fast._pair_cells` computes its table rows in the type of the pair indices (`fast.vertex_view`
    passes int32, `fast.pair_indices32`, when every table has fewer than 2³¹ rows): every output —
    the W_r rows and weights, the θ nodes, the visibility bag, cos⁺θo, the SH basis — equals the
    int64 computation's bit for bit (the rows as values), including directions below the horizon
    and at the table borders."""
    from methods.ptt import fast as F

    g = torch.Generator().manual_seed(13)
    n, R, nv, T, Tv, nt, L = 777, 3, 300, 12, 8, 5, 4
    frames = torch.linalg.qr(torch.randn(n, 3, 3, generator=g))[0]
    pos = (torch.randn(n, 3, generator=g) * 2.0).T.contiguous()
    cam = torch.tensor([0.3, 4.0, -1.0])
    r = torch.randint(0, R, (n,), generator=g)
    v = torch.randint(0, nv, (n,), generator=g)
    vis = torch.rand(nv * Tv * Tv, L, generator=g)
    frame = frames.reshape(n, 9).T.contiguous()
    for order in (0, 3):
        a = F._pair_cells(pos, frame, cam, r, v, T, Tv, nt, True, order, vis)
        b = F._pair_cells(pos, frame, cam, r.to(torch.int32), v.to(torch.int32), T, Tv, nt, True, order, vis)
        assert len(a) == len(b)
        for x, y in zip(a, b):
            if x.dtype == torch.int64:
                assert y.dtype == torch.int32 and torch.equal(x, y.long())
            else:
                assert torch.equal(x, y)
    z = a[6]
    assert bool((z == 0).any()) and bool((z > 0).any())  # both sides of the horizon


@pytest.mark.parametrize("S2", [1, 4])
def test_native_shade_loop_is_the_compiled_shade_block_bit_for_bit(S2, monkeypatch):
    """``native.shade_pixels`` (the C loop `fast.shade_cells` takes) gives the same bits as the
    compiled `fast.shade_block` on the rows of the perf suite's configuration (width 16: 4 lobes, no
    u column — the loop's body with fixed lane selects) at 1 and 2 threads (the pixel range split), and the eager `fast._shade_block` to
    round-off on widths 32 and 48 (the u column; the generic loop); with negative Gouraud sums,
    misses (face −1, the zero face of `fast.miss_face_pairs`; a face past the table reads it too) and
    the barycentrics as the G-buffer stores them (columns of a (2, n) array) and row-major; it
    declines (None) arguments it does not read. One compiled variant per S2 (CI compiles it cold;
    S2 = 4 shares its shapes with `test_native_mirror_cells_are_the_compiled_cells_bit_for_bit`)."""
    from methods.ptt import fast as F
    from methods.ptt import native as N

    if not N.available():
        pytest.skip("no C compiler")
    monkeypatch.setattr(N, "_MIN_PIXELS_PER_THREAD", 16)
    n = S2 * (4098 if S2 == 4 else 3001)
    g, n_pairs, L, face_pairs, face, bary, normal, wo, _ = _random_shading_inputs(n, 3)
    face = torch.where(torch.rand(n, generator=g) < 0.05, -1, face)
    fpm = torch.cat([face_pairs, torch.full((1, 3), n_pairs, dtype=face_pairs.dtype)])
    H, W = 16, 32
    for L, extra in ((4, 0), (4, 3), (14, 0)):
        maps = [_FakeEnv(torch.rand(H, W, 3, generator=g) * 4.0) for _ in range(L)]
        width, erows, table, lanes, r, fx, fy = _shade_tables(g, maps, 3 + 3 * L + extra, L, n_pairs, H, W, n)
        got = N.shade_pixels(face, bary, r, fx, fy, fpm, table, erows, lanes, W, S2)
        if width == 16:
            want = F.shade_block(face, bary, r, fx, fy, fpm, table, erows, lanes, W, S2)
            for threads in (1, 2):
                torch.set_num_threads(threads)
                try:
                    for b in (bary, bary.T.contiguous().T):
                        out = N.shade_pixels(face, b, r, fx, fy, fpm, table, erows, lanes, W, S2)
                        assert torch.equal(out, want), (threads, float((out - want).abs().max()))
                finally:
                    torch.set_num_threads(1)
        past = face.clone()
        past[face == -1] = fpm.shape[0] + 5
        assert torch.equal(N.shade_pixels(past, bary, r, fx, fy, fpm, table, erows, lanes, W, S2), got)
        eager = F._shade_block(face, bary, r, fx, fy, fpm, table, erows, lanes, W, S2)
        torch.testing.assert_close(got, eager, rtol=1e-5, atol=1e-5 * float(eager.abs().max()))
        assert bool((got.abs() > 0).any())
    assert N.shade_pixels(face[:5], bary[:5], r[:5], fx[:5], fy[:5], fpm, table, erows, lanes, W, 2) is None
    assert N.shade_pixels(face.int(), bary, r, fx, fy, fpm, table, erows, lanes, W, S2) is None
    assert N.shade_pixels(face, bary, r.long(), fx, fy, fpm, table, erows, lanes, W, S2) is None


def test_pixel_stage_takes_the_native_loop_with_the_same_bits(monkeypatch):
    """`fast.shade_pixels_fused` takes the native loops (`fast.USE_NATIVE`): the one-pass
    ``native.shade_mirror``, or without the native cells ``native.shade_pixels`` after the compiled
    cells — the same image bit for bit (each route is compared with the compiled kernels by the tests
    around this one), and the eager `fast.shade_samples` + `fast.box_filter` to round-off."""
    from methods.ptt import fast as F
    from methods.ptt import native as N

    if not N.available():
        pytest.skip("no C compiler")
    S2, n_pixels = 4, 1 << 10
    g, n_pairs, L, face_pairs, face, bary, normal, wo, env = _random_shading_inputs(S2 * n_pixels, 4)
    table = torch.randn(n_pairs + 1, 3 + 3 * L, generator=g)
    calls = []
    def recording(name, real):
        def call(*a):  # the route that produced the image (shade_mirror is tried first and returns
            out = real(*a)  # None where the native cells do not run, e.g. Inductor on AVX-512)
            if out is not None:
                calls.append(name)
            return out
        return call

    for name in ("shade_pixels", "shade_mirror"):
        monkeypatch.setattr(N, name, recording(name, getattr(N, name)))
    images = [F.shade_pixels_fused(face_pairs, table, face, bary, normal, wo, env, L, S2)]
    assert calls[0] == ("shade_mirror" if N.cells_available() else "shade_pixels")
    monkeypatch.setattr(N, "cells_available", lambda: False)
    images.append(F.shade_pixels_fused(face_pairs, table, face, bary, normal, wo, env, L, S2))
    assert calls[-1] == "shade_pixels"
    assert torch.equal(images[0], images[1])
    ref = F.box_filter(F.shade_samples(face_pairs, table, face, bary, normal, wo, env, L), n_pixels, 1, S2)
    torch.testing.assert_close(images[0].view(n_pixels, 1, 3), ref, rtol=1e-5, atol=1e-5 * float(ref.abs().max()))


def test_native_mirror_cells_are_the_compiled_cells_bit_for_bit(monkeypatch):
    """``native.mirror_cells`` (Inductor's vector operations one for one for the ISA it vectorises for
    here — AVX2, 8 lanes, or AVX-512, 16 —, the same polynomial acos / atan2; on an AVX-512 build the
    AVX2 body too) gives the bits of the compiled
    `fast.mirror_cells_block` — first row, fx, fy — on two grids and rotations, with the normals
    row-major and the view directions as the G-buffer stores them (columns of a (3, n) array) or
    row-major, n a multiple of 8 but not of 16 (AVX-512: a last vector of 8 samples, as the compiled
    kernel's tail); a NaN normal gives row 0 in both. And
    ``native.shade_mirror`` (the cells and the shading in one pass, pixels split over two threads)
    gives the image of `fast.mirror_cells_block` + `fast.shade_block`, bit for bit."""
    from methods.ptt import fast as F
    from methods.ptt import native as N

    if not N.cells_available():
        pytest.skip("no native cells for the ISA Inductor vectorises for here")
    g = torch.Generator().manual_seed(13)
    n = 20_008
    normal = torch.randn(n, 3, generator=g) * (0.5 + torch.rand(n, 1, generator=g))
    normal[::997] = torch.tensor([0.0, 1.0, 0.0])  # mirror directions on the map's axis / seam
    wo = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1)
    wo[::997] = torch.tensor([0.0, 1.0, 0.0])
    normal[5] = float("nan")
    ok = torch.arange(n) != 5
    # the normals row-major (the G-buffer's: the deinterleaving loads, ``aos3``), as columns of a (3, n)
    # array and with a row stride of 4 (the one-float-at-a-time loads)
    layouts = (normal, normal.T.contiguous().T, torch.cat([normal, torch.zeros(n, 1)], 1)[:, :3])
    sl = N._sleef()
    # the cells of the ISA Inductor vectorises for, and the AVX2 body (cells8) where the library is built for
    # AVX-512 too: the polynomial angles are the same bits on 8 or 16 lanes
    bodies = [sl] + ([(sl[0], sl[1], 0)] if sl[2] else [])
    for (H, W), w in (((256, 512), wo.T.contiguous().T), ((33, 70), wo)):  # the G-buffer's wo layout; row-major
        to_world = torch.linalg.qr(torch.randn(3, 3, generator=g, dtype=torch.float64))[0].float().contiguous()
        want = F.mirror_cells_block(normal, w, to_world, H, W)
        for body in bodies:
            monkeypatch.setattr(N, "_sleef", lambda body=body: body)
            for nrm in layouts:
                got = N.mirror_cells(nrm, w, to_world, H, W)
                assert got[0].dtype == torch.int32 and torch.equal(got[0], want[0])
                assert all(torch.equal(a[ok], b[ok]) for a, b in zip(got[1:], want[1:]))
        monkeypatch.setattr(N, "_sleef", lambda: sl)
    assert N.mirror_cells(normal[:12], wo[:12], to_world, H, W) is None  # not a multiple of 8

    monkeypatch.setattr(N, "_MIN_PIXELS_PER_THREAD", 16)
    S2, n_pix = 4, 4098
    g, n_pairs, L, face_pairs, face, bary, normal, wo, env = _random_shading_inputs(S2 * n_pix, 5)
    face = torch.where(torch.rand(S2 * n_pix, generator=g) < 0.05, -1, face)
    fpm = torch.cat([face_pairs, torch.full((1, 3), n_pairs, dtype=face_pairs.dtype)])
    C = 3 + 3 * L
    width = F.table_width(C)
    maps = [_FakeEnv(torch.rand(env.H, env.W, 3, generator=g) * 4.0, env.to_world) for _ in range(L)]
    erows = F.env_rows(F.env_stack(maps, width), width)
    table = F.padded(torch.randn(n_pairs + 1, C, generator=g), width)
    table[-1] = 0.0
    lanes = F._lane_masks(C, L, width)
    r, fx, fy = F.mirror_cells_block(normal, wo, env.to_world, env.H, env.W)
    want = F.shade_block(face, bary, r, fx, fy, fpm, table, erows, lanes, env.W, S2)
    for threads in (1, 2):
        torch.set_num_threads(threads)
        try:
            got = N.shade_mirror(normal, wo, env.to_world, env.H, face, bary, fpm, table, erows, lanes, env.W, S2)
        finally:
            torch.set_num_threads(1)
        assert torch.equal(got, want)


@pytest.mark.parametrize("native", [True, False])
def test_referenced_pairs_are_the_pairs_of_the_hit_faces(native, monkeypatch):
    """`fast.referenced_pairs` (the native loop, or its torch twin): sel is the sorted set of the
    corners' pairs of the faces the samples lie on (misses, face −1, read none), and fpc maps every
    face corner onto its pair's position in sel — so a sample's three rows of the compact table are
    its rows of the full one — with the miss face (last row) and pairs no sample reads at m, the
    compact table's zero row. Both implementations give the same integers; also with every sample a
    miss, and with one face only."""
    from methods.ptt import fast as F
    from methods.ptt import native as N

    if native and not N.available():
        pytest.skip("no C compiler")
    monkeypatch.setattr(F, "USE_NATIVE", native)
    g = torch.Generator().manual_seed(21)
    n_pairs, M, n = 500, 700, 4096
    st = F.FastStatic(torch.zeros(1), torch.zeros(1), torch.zeros(n_pairs, dtype=torch.int64), torch.zeros(1), None,
                      torch.randint(0, n_pairs, (M, 3), generator=g))
    face = torch.randint(0, M // 3, (n,), generator=g)  # a third of the faces: some pairs unread
    face[::7] = -1
    for f in (face, torch.full((n,), -1), torch.full((n,), 5)):
        sel, fpc = F.referenced_pairs(st, f)
        hit = f[f >= 0]
        want = torch.unique(st.face_pairs[hit]) if hit.numel() else torch.zeros(0, dtype=torch.int64)
        assert torch.equal(sel, want)
        m = int(sel.numel())
        assert fpc.shape == (M + 1, 3) and fpc.dtype == torch.int64
        assert torch.equal(fpc[-1], torch.full((3,), m))
        assert torch.equal(sel[fpc[hit]], st.face_pairs[hit])  # every read corner: its own pair's position
        unread = ~torch.isin(st.face_pairs, sel)
        assert bool((fpc[:-1][unread] == m).all())
        if native:
            monkeypatch.setattr(F, "USE_NATIVE", False)
            s2, f2 = F.referenced_pairs(st, f)
            monkeypatch.setattr(F, "USE_NATIVE", True)
            assert torch.equal(sel, s2) and torch.equal(fpc, f2)
    if native:  # the samples split over 2 and 3 threads (each marking its own copy): the same integers
        big = torch.randint(-1, M, (1 << 17,), generator=g)
        big[: 1 << 16] = torch.randint(0, M // 4, (1 << 16,), generator=g)  # faces only the first half reads
        monkeypatch.setattr(F, "USE_NATIVE", False)
        want = F.referenced_pairs(st, big)
        monkeypatch.setattr(F, "USE_NATIVE", True)
        n_threads = torch.get_num_threads()
        try:
            for t in (1, 2, 3):
                torch.set_num_threads(t)
                got = F.referenced_pairs(st, big)
                assert torch.equal(got[0], want[0]) and torch.equal(got[1], want[1]), t
        finally:
            torch.set_num_threads(n_threads)


@pytest.mark.parametrize("name", ["chess", "creature"])
def test_full_table_renders_the_compact_table_frames_bit_for_bit(name, monkeypatch, small):
    """`method.FULL_TABLE` (session 38): the referenced pairs' rows written at the pairs' own positions
    (`fast.referenced_view`: ``native.referenced_sel`` + ``native.vertex_rows(..., rows_at=True)``) and
    read through the static face corners render, bit for bit, the frames of the compact table read
    through the remapped corners (`fast.referenced_pairs`), at 1 and 2 threads, V and VB frames, with
    misses; the route is taken (bounces 0, lobes: the perf suite's shape); sel is `referenced_pairs`'
    and the table's rows at sel are the compact rows, its last row 0."""
    from methods.ptt import fast as F
    from methods.ptt import method as PM
    from methods.ptt import native as N

    if not (F.native_shading() and N.cells_available()):
        pytest.skip("no native sample stage / cells")
    monkeypatch.setattr(N, "_MIN_PAIRS_PER_THREAD", 8)
    monkeypatch.setattr(N, "_MIN_SAMPLES_PER_THREAD", 64)
    scene = get_scene(name, "test")
    m = PTT(**{**TINY, **VARIANTS[name], "n_wi": 8, "bounces": 0})  # 3K = 24 lanes: the native rows' 8-lane blocks
    m.precompute(scene)
    calls = []
    real = F.referenced_view

    def recording(*a):
        out = real(*a)
        calls.append(a if out is not None else None)
        return out

    monkeypatch.setattr(F, "referenced_view", recording)
    monkeypatch.setattr(PM, "VIEW_FRAME", False)  # the Python route's calls (VIEW_FRAME: tests/methods/ptt/test_view_frame.py)
    for kind in ("V", "VB"):
        for i, f in enumerate(make_sequence(scene, kind, n_frames=2, seed=4)):
            f = small(f)
            gb = make_gbuffer(scene, f, 2)
            if i == 1:  # misses, as the G-buffer writes them
                miss = torch.zeros_like(gb.hit)
                miss[5::37] = True
                gb = dataclasses.replace(gb, hit=gb.hit & ~miss, face=torch.where(miss, -1, gb.face))
            for threads in (1, 2):
                torch.set_num_threads(threads)
                try:
                    monkeypatch.setattr(PM, "FULL_TABLE", True)
                    n_calls = len(calls)
                    a = m.render(f, gb)
                    assert len(calls) == n_calls + 1 and calls[-1] is not None, "the FULL_TABLE route was not taken"
                    monkeypatch.setattr(PM, "FULL_TABLE", False)
                    b = m.render(f, gb)
                finally:
                    torch.set_num_threads(1)
                assert torch.equal(a, b), f"{name} {kind} frame {i} threads {threads}: {(a - b).abs().max()}"
            st, face, cam, Wr, E, T, K, lobes, width = calls[-1]
            fp, table = real(st, face, cam, Wr, E, T, K, lobes, width)
            sel, fpc = F.referenced_pairs(st, face)
            assert torch.equal(N.referenced_sel(face, st.face_pairs, st.pair_v.numel()), sel)
            compact = F.vertex_view(st, cam, Wr, E, T, K, lobes, width, pairs=sel)
            assert fp is F.miss_face_pairs(st) and table.shape == (st.pair_v.numel() + 1, compact.shape[1])
            assert torch.equal(table[sel], compact[:-1]) and not bool(table[-1].any())


def test_view_rows_of_the_referenced_pairs_are_the_full_rows_bit_for_bit(monkeypatch, small):
    """`fast.vertex_view(..., pairs=sel)` (the compiled per-pair loops on the pairs ``sel`` only, their
    count symbolic) gives, bit for bit, the rows of those pairs in the full table, and the zero row
    last (also for 0 and 1 pairs, padded inside); and a frame rendered through the referenced pairs
    (`method.REFERENCED_PAIRS`, the faces remapped onto the compact table) is the frame rendered from
    the full table, bit for bit — with and without the one-bounce column, with misses."""
    from methods.ptt import fast as F
    from methods.ptt import method as PM

    if not F.native_shading():
        pytest.skip("no native sample stage")
    scene = get_scene("chess", "test")
    calls = []
    real = F.referenced_pairs
    monkeypatch.setattr(F, "referenced_pairs", lambda *a: calls.append(1) or real(*a))
    monkeypatch.setattr(PM, "FULL_TABLE", False)  # the compact table (FULL_TABLE's: the next test)
    for bounces in (0, 1):
        m = PTT(**{**TINY, **VARIANTS["chess"]}, bounces=bounces)
        m.precompute(scene)
        frames = [small(f) for f in make_sequence(scene, "V", n_frames=3, seed=3)]
        for i, f in enumerate(frames):
            gb = make_gbuffer(scene, f, 2)
            if i == 2:  # misses, as the G-buffer writes them
                miss = torch.zeros_like(gb.hit)
                miss[3::41] = True
                gb = dataclasses.replace(gb, hit=gb.hit & ~miss, face=torch.where(miss, -1, gb.face))
            monkeypatch.setattr(PM, "REFERENCED_PAIRS", True)
            n_calls = len(calls)
            a = m.render(f, gb)
            assert len(calls) == n_calls + 1, "the referenced-pairs route was not taken"
            monkeypatch.setattr(PM, "REFERENCED_PAIRS", False)
            b = m.render(f, gb)
            assert torch.equal(a, b), f"bounces {bounces} frame {i}: {(a - b).abs().max()}"
        # the rows themselves, of the last frame's pairs and of 0 / 1 / 2 pairs
        st = m._fast_static()
        E, I1 = m._f_E
        Wr, ar = m._f_tabs
        L = len(m.config["lobe_degrees"])
        from methods.core.zh import expand_bands

        lobes = dict(ar=ar, n_theta=m.lobe_table.theta.shape[0], Tv=m.lobe_vis.shape[-1],
                     vis=m.lobe_vis.permute(0, 2, 3, 1).reshape(-1, L), I1=I1,
                     f=None if I1 is None else expand_bands(m.lobe_sh), order=m.config["sh_order"])
        C = 3 + 3 * L + (3 if I1 is not None else 0)
        width = F.table_width(C)
        T, K = m.factors.W_tab.shape[-1], m.factors.K
        cam = torch.as_tensor(frames[-1].camera.origin, dtype=torch.float32)
        full = F.vertex_view(st, cam, Wr, E, T, K, lobes, width)
        sel, _ = F.referenced_pairs(st, gb.face)
        assert 2 <= sel.numel() < st.pair_v.numel()
        for s in (sel, sel[:0], sel[5:6], sel[-2:]):
            sub = F.vertex_view(st, cam, Wr, E, T, K, lobes, width, pairs=s)
            assert sub.shape == (s.numel() + 1, full.shape[1])
            assert torch.equal(sub[:-1], full[s]) and not bool(sub[-1].any())


@pytest.mark.parametrize("n_wi", [8, 24])
def test_native_vertex_rows_are_the_compiled_rows_bit_for_bit(n_wi, monkeypatch, small):
    """``native.vertex_rows`` (`fast.vertex_view(..., pairs=sel)` with lobes and no SH column as one C
    pass: the compiled passes' products and sums in their order, the same Sleef atan2 / acos, B's lane
    sums as their reduction) gives the bits of the compiled `fast.pair_cells_of` + `fast.pair_rows`
    (``native.vertex_rows`` switched off) for the referenced pairs of a frame and for 1, 2, 7, 33 and
    every pair, from cameras around the scene and close to it (pairs below their vertex's horizon), at
    1 and 2 threads, padded to the sample stage's width or not; `fast.vertex_view` takes it. K = 8 and
    24 (24- and 72-lane rows: on AVX-512 the compiled reduction's 16-lane accumulator, with a masked
    last block of 8, sums a channel's lanes in another order than AVX2's 8-lane one for K = 24)."""
    from methods.ptt import fast as F
    from methods.ptt import native as N

    if not N.cells_available():
        pytest.skip("no native cells for the ISA Inductor vectorises for here")
    monkeypatch.setattr(N, "_MIN_PAIRS_PER_THREAD", 8)
    scene = get_scene("chess", "test")
    m = PTT(**{**TINY, **VARIANTS["chess"], "n_wi": n_wi}, bounces=0)  # 3K-lane rows (the native loop reads 8-lane blocks)
    m.precompute(scene)
    frames = [small(f) for f in make_sequence(scene, "V", n_frames=2, seed=5)]
    gb = make_gbuffer(scene, frames[0], 2)
    m.render(frames[0], gb)
    st = m._fast_static()
    E, I1 = m._f_E
    assert I1 is None
    Wr, ar = m._f_tabs
    L = len(m.config["lobe_degrees"])
    lobes = dict(ar=ar, n_theta=m.lobe_table.theta.shape[0], Tv=m.lobe_vis.shape[-1],
                 vis=m.lobe_vis.permute(0, 2, 3, 1).reshape(-1, L), I1=None, f=None, order=m.config["sh_order"])
    T, K = m.factors.W_tab.shape[-1], m.factors.K
    assert (3 * K) % 8 == 0
    sel, _ = F.referenced_pairs(st, gb.face)
    n = st.pair_v.numel()
    every = torch.arange(n)
    calls = []
    real = N.vertex_rows
    monkeypatch.setattr(N, "vertex_rows", lambda *a: calls.append(1) or real(*a))
    g = torch.Generator().manual_seed(3)
    centre = m.V.mean(0)
    cams = [torch.as_tensor(f.camera.origin, dtype=torch.float32) for f in frames]
    cams += [centre + torch.randn(3, generator=g) * s for s in (0.05, 0.3, 3.0)]
    for cam in cams:
        for pairs in (sel, every, every[7:8], every[-2:], every[3:10], torch.randperm(n, generator=g)[:33].sort()[0]):
            for width in (0, F.table_width(3 + 3 * L)):
                got = []
                for threads in (1, 2):
                    torch.set_num_threads(threads)
                    try:
                        k = len(calls)
                        got.append(F.vertex_view(st, cam, Wr, E, T, K, lobes, width, pairs=pairs))
                        assert len(calls) == k + 1
                    finally:
                        torch.set_num_threads(1)
                monkeypatch.setattr(N, "vertex_rows", lambda *a: None)
                want = F.vertex_view(st, cam, Wr, E, T, K, lobes, width, pairs=pairs)
                monkeypatch.setattr(N, "vertex_rows", lambda *a: calls.append(1) or real(*a))
                for out in got:
                    assert out.shape == want.shape and torch.equal(out, want), float((out - want).abs().max())
    assert bool((got[0][:, :3] != 0).any()) and bool((got[0][:, 3:] != 0).any())


@pytest.mark.parametrize("n_pix", [4098, 1002])
def test_lean_pixel_body_is_the_general_body_bit_for_bit(n_pix, monkeypatch):
    """``native.shade_mirror``'s AVX-512 body for the perf suite's rows (``lean16``: width 16 without u
    lanes, S2 = 4, the barycentrics as the G-buffer's columns; `native.LEAN`) gives the bits of the
    general body (``LEAN`` off) and of the compiled `fast.shade_block` on the compiled cells, at 1, 2
    and 3 threads (one range of whole runs per thread, `native.RR_PIXELS` 0, the default; and chunks of
    256 pixels dealt round robin): with misses (face −1
    and past the table), negative Gouraud sums (max(0, ·) on the B lanes), a NaN on a B lane of some
    rows (kept, as Inductor's maximum), runs of 128 pixels with a last run that ends in a part group
    of 8 pixels (4098 = 32 · 128 + 2; 1002 = 7 · 128 + 13 · 8 + 2) and chunks of 256 pixels with a
    part chunk last."""
    from methods.ptt import fast as F
    from methods.ptt import native as N

    if not N.lean_available():
        pytest.skip("no AVX-512 build of the native cells")
    monkeypatch.setattr(N, "_MIN_PIXELS_PER_THREAD", 16)
    S2 = 4
    g, n_pairs, L, face_pairs, face, bary, normal, wo, env = _random_shading_inputs(S2 * n_pix, 7)
    face = torch.where(torch.rand(S2 * n_pix, generator=g) < 0.05, -1, face)
    past = face.clone()
    past[7::501] = 10_000  # past the table: the zero face too (the native loops; the compiled one reads -1)
    face[7::501] = -1
    bary = bary.T.contiguous().T  # the G-buffer's layout: b1, b2 contiguous
    fpm = torch.cat([face_pairs, torch.full((1, 3), n_pairs, dtype=face_pairs.dtype)])
    C = 3 + 3 * L
    width = F.table_width(C)
    assert width == 16 and L == 4
    maps = [_FakeEnv(torch.rand(env.H, env.W, 3, generator=g) * 4.0, env.to_world) for _ in range(L)]
    erows = F.env_rows(F.env_stack(maps, width), width)
    table = F.padded(torch.randn(n_pairs + 1, C, generator=g), width)
    table[3:n_pairs:37, 0] = float("nan")  # a B lane: max(0, NaN) is NaN
    table[-1] = 0.0
    lanes = F._lane_masks(C, L, width)
    r, fx, fy = F.mirror_cells_block(normal, wo, env.to_world, env.H, env.W)
    want = F.shade_block(face, bary, r, fx, fy, fpm, table, erows, lanes, env.W, S2)
    nan = torch.isnan(want)
    assert bool(nan.any()) and bool((~nan).any())

    def same(a, b):
        return torch.equal(torch.isnan(a), torch.isnan(b)) and torch.equal(a[~torch.isnan(a)], b[~torch.isnan(b)])

    for lean in (False, True):
        monkeypatch.setattr(N, "LEAN", lean)
        for threads, rr in ((1, 256), (2, 256), (3, 256), (2, 0), (3, 0)):  # RR_PIXELS 0: a range per thread
            monkeypatch.setattr(N, "RR_PIXELS", rr)
            torch.set_num_threads(threads)
            try:
                got = N.shade_mirror(normal, wo, env.to_world, env.H, past, bary, fpm, table, erows, lanes, env.W, S2)
            finally:
                torch.set_num_threads(1)
            assert same(got, want), (lean, threads, rr, float((got - want)[~nan].abs().max()))


def test_lean_pixel_body_renders_the_same_frames(monkeypatch, small):
    """A PTT frame in the perf suite's shape (lobes, no bounce terms, 2 × 2 samples per pixel: rows of
    width 16 without u lanes, the G-buffer's barycentric columns) reaches ``native.shade_mirror`` with
    the arguments the AVX-512 body ``lean16`` takes, and renders the same image bit for bit with
    `native.LEAN` on and off, equal to the reference path to float32 round-off."""
    from methods.ptt import native as N

    if not N.lean_available():
        pytest.skip("no AVX-512 build of the native cells")
    scene = get_scene("chess", "test")
    m = PTT(**{**TINY, **VARIANTS["chess"]}, bounces=0)
    m.precompute(scene)
    seen, real = [], N.shade_mirror

    def recording(*a):
        seen.append(a)
        return real(*a)

    monkeypatch.setattr(N, "shade_mirror", recording)
    from methods.ptt import method as PM

    monkeypatch.setattr(PM, "VIEW_FRAME", False)  # the Python route's calls (VIEW_FRAME: test_view_frame.py)
    for kind in ("V", "VB"):
        for f in make_sequence(scene, kind, n_frames=2, seed=3):
            f = small(f)
            gb = make_gbuffer(scene, f, 2)
            images = []
            for lean in (True, False):
                monkeypatch.setattr(N, "LEAN", lean)
                images.append(m.render(f, gb))
            assert seen, "the frame did not reach native.shade_mirror"
            face, bary, lanes, S2 = seen[-1][4], seen[-1][5], seen[-1][9], seen[-1][11]
            width = int(seen[-1][7].shape[1])
            assert S2 == 4 and width == 16 and bary[:, 0].stride(0) == 1 and face.shape[0] % 8 == 0
            assert not bool(lanes[1, :16].any()) and not bool(lanes[0, 8:16].any())  # plain16's rows
            assert torch.equal(images[0], images[1])
            ref = m._render_reference(f, gb)
            torch.testing.assert_close(images[0], ref, rtol=1e-5, atol=2e-6 * max(float(ref.abs().max()), 1.0))


def test_fast_coords_are_the_per_material_coords(monkeypatch):
    """`PTT.coords` with FAST_COORDS (session 40: `LobeBasis.coords_rows`, and the last H handed back
    while every region's material is the very object of the last call) equals the per-material
    ``basis.coords`` path bit for bit over VB / V frames; a changed material object in any one region —
    equal or not — is looked up again."""
    from methods.ptt import method as _method

    scene = get_scene("chess", "test")
    m = PTT(**TINY, bounces=0)
    m.precompute(scene)
    frames = make_sequence(scene, "VB", n_frames=4, seed=5) + make_sequence(scene, "V", n_frames=2, seed=5)
    monkeypatch.setattr(_method, "FAST_COORDS", False)
    m._reset_cache()
    want = [m.coords(f.materials) for f in frames]
    monkeypatch.setattr(_method, "FAST_COORDS", True)
    m._reset_cache()
    for f, w in zip(frames, want):
        H = m.coords(f.materials)
        assert H.dtype == torch.float32 and torch.equal(H, w)
        assert m.coords(f.materials) is H  # the same objects: the same H
    mats = dict(frames[1].materials)
    H1 = m.coords(mats)
    for r in m.regions:  # an equal copy in one region: looked up (by value), the same numbers
        other = dict(mats)
        other[r] = dataclasses.replace(mats[r])
        H2 = m.coords(other)
        assert H2 is not H1 and torch.equal(H2, H1)
    for i, r in enumerate(m.regions):  # another material in one region (the last, too): that region's rows change
        other = dict(mats)
        other[r] = frames[2].materials[r]
        H2 = m.coords(other)
        assert torch.equal(H2[i], want[2][i]) and torch.equal(H2[torch.arange(len(m.regions)) != i],
                                                               want[1][torch.arange(len(m.regions)) != i])
        m.coords(mats)
