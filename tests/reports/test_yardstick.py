"""The one-yardstick terms-vs-exponent study (`reports.studies.terms_vs_exponent`) and its registry
(`methods.studies.register_term_ladder`): the search on stand-in methods with known error curves,
the CSV's shape and monotonicity flags, and one quick run of every registered ladder."""
from __future__ import annotations

import csv
import math

import pytest
import torch

from methods import studies as MS
from methods.base import Method
from reports import studies as S
from reports.palette import METHOD_COLORS, method_color


@pytest.fixture
def clean_ladders():
    saved = dict(MS.TERM_LADDERS)
    yield
    MS.TERM_LADDERS.clear()
    MS.TERM_LADDERS.update(saved)


class _Fake(Method):
    """Renders the (constant 1) reference × (1 + err(s, K)): its relative RMSE is err(s, K)."""

    name = "fake"
    err = staticmethod(lambda s, k: s / (10.0 * k))

    def __init__(self, *, terms: int):
        super().__init__(terms=terms)
        self.precomputes = 0

    def precompute(self, scene) -> None:
        self.s = scene["s"]

    def render(self, frame, gbuffer):
        return torch.full((4, 4, 3), 1.0 + type(self).err(frame["s"], self.config["terms"]))

    def memory(self):
        return {"x": 100 * self.config["terms"]}


class _Ref:
    image = torch.ones(4, 4, 3)


def _fake_frame(scene_name, region, s, cfg):
    return S._Frame({"s": s}, {"s": s}, None, _Ref(), torch.ones(4, 4, dtype=torch.bool), 1.0, 0.001, 10)


def _ladder(name, err, renders, scan=False):
    class M(_Fake):
        pass

    M.err = staticmethod(err)

    def make(config, region):
        renders.append((name, config["terms"]))
        return M(**config)

    return MS.register_term_ladder(name, [dict(terms=k) for k in range(1, 65)], make, replace=True, scan=scan)


def test_register_term_ladder_validates(clean_ladders):
    make = lambda c, r: None  # noqa: E731
    with pytest.raises(ValueError, match="ladder"):
        MS.register_term_ladder("x", [], make)
    with pytest.raises(ValueError, match="decrease"):
        MS.register_term_ladder("x", [dict(terms=4), dict(terms=2)], make)
    with pytest.raises(ValueError, match="make"):
        MS.register_term_ladder("x", [dict(terms=1)], 3)
    with pytest.raises(ValueError, match=">= 1"):
        MS.register_term_ladder("x", [dict(order=2)], make, lambda c: 0)
    lad = MS.register_term_ladder("x", [dict(order=n) for n in (2, 3, 4)], make, lambda c: c["order"] ** 2)
    assert [lad.terms_of(c) for c in lad.quick] == [4, 9]  # default quick ladder: the first two rungs
    with pytest.raises(ValueError, match="already"):
        MS.register_term_ladder("x", [dict(terms=1)], make)


def test_every_method_has_a_ladder():
    for name in ("inout", "zh_shadow", "triple_product", "ptt"):
        lad = MS.TERM_LADDERS[name]
        assert len(lad.ladder) >= 7 and lad.quick, name
        terms = [lad.terms_of(c) for c in lad.ladder]
        assert terms == sorted(terms) and terms[-1] > terms[0]
        # fine: <= 2x between rungs, except SH order 2 -> 3 (4 -> 9 terms: no order in between)
        assert max(b / a for a, b in zip(terms, terms[1:])) <= 2.25, name
    assert MS.TERM_LADDERS["zh_shadow"].material_at_render
    # the lobe Mitsuba renders (cos θ_i included), as every other ladder: the paper's lobe is another BRDF
    zh = MS.TERM_LADDERS["zh_shadow"]
    assert all(c["specular"] == "cosine" for c in zh.ladder + zh.quick)
    assert all(zh.make(dict(c), "sphere").config["specular"] == "cosine" for c in zh.ladder[:1])


def test_search_matches_exhaustive_and_csv_shape(tmp_path, monkeypatch, clean_ladders):
    """err = 0.9 s / (10 K): the smallest K reaching t is ceil(0.09 s / t) (not reached beyond K = 64;
    0.9: no answer sits exactly on a float32 boundary);
    the bisected answer equals the exhaustive one, with the rung below missing the target."""
    monkeypatch.setattr(S, "_phong_frame", _fake_frame)
    MS.TERM_LADDERS.clear()
    renders: list = []
    _ladder("fake", lambda s, k: 0.09 * s / k, renders)
    # non-monotone in s: at s = 8 the error is 4x smaller than the smooth curve
    _ladder("dip", lambda s, k: 0.09 * (s / 4 if s == 8 else s) / k, renders)
    exps = (1, 2, 4, 8, 16, 32, 64, 128, 256)
    cfg = S.YardstickConfig(scenes=(("a", "r"), ("b", "r")), exponents=exps, targets=(0.05, 0.1), ref_spp=2)
    files = S.terms_vs_exponent(tmp_path, config=cfg)
    assert {f.name for f in files} == {"terms_vs_exponent.csv", "terms_vs_exponent.png", "ladder_evaluations.csv",
                                       "summary.json"}
    rows = list(csv.DictReader(open(tmp_path / "terms_vs_exponent.csv")))
    assert len(rows) == 2 * 2 * len(exps) * 2  # scenes × methods × exponents × targets
    assert {(r["scene"], r["method"], float(r["exponent"]), float(r["target"])) for r in rows} == {
        (sc, m, float(s), t) for sc in "ab" for m in ("fake", "dip") for s in exps for t in (0.05, 0.1)}
    for r in rows:
        s, t = float(r["exponent"]), float(r["target"])
        se = s / 4 if r["method"] == "dip" and s == 8 else s
        want = math.ceil(0.09 * se / t)
        if want > 64:
            assert r["reached"] == "False" and int(r["terms"]) == 64  # plotted at the largest rung tried
        else:
            assert r["reached"] == "True" and int(r["terms"]) == want, r
            assert float(r["rel_rmse"]) <= t
            assert float(r["bytes_per_vertex"]) == 10 * want  # 100 B per term / 10 vertices
            if want > 1:
                assert int(r["prev_terms"]) == want - 1 and float(r["prev_rel_rmse"]) > t
        flagged = r["monotone"] == "False"
        # fake is monotone; dip needs fewer terms at s = 8 than at s = 4 (when resolved by the ladder)
        assert flagged == (r["method"] == "dip" and s == 8 and math.ceil(0.18 / t) < math.ceil(0.36 / t)), r
        assert bool(r["note"]) == flagged
    # cached per (method, rung, s): no render repeated
    evals = list(csv.DictReader(open(tmp_path / "ladder_evaluations.csv")))
    keys = [(e["scene"], e["method"], e["exponent"], e["rung"]) for e in evals]
    assert len(keys) == len(set(keys)) == len(renders)
    assert len(renders) < 0.25 * 2 * 2 * len(exps) * 64  # far fewer renders than the whole ladder


def test_quick_terms_vs_exponent_every_ladder(tmp_path):
    """The real ladders' quick rungs on sphere_plane (64-spp reference): the CSV has every (method,
    s, target) and each method's terms are non-decreasing in s or flagged."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        MS.run_study("terms-vs-exponent", tmp_path, quick=True)
    finally:
        torch.set_num_threads(n)
    cfg = S.YARDSTICK_QUICK
    rows = list(csv.DictReader(open(tmp_path / "terms_vs_exponent.csv")))
    names = sorted(MS.TERM_LADDERS)
    assert len(rows) == len(names) * len(cfg.exponents) * len(cfg.targets) * len(cfg.scenes)
    assert sorted({r["method"] for r in rows}) == names
    for m in names:
        for t in cfg.targets:
            rr = sorted((r for r in rows if r["method"] == m and float(r["target"]) == t),
                        key=lambda r: float(r["exponent"]))
            most = 0
            for r in rr:
                e = float(r["rel_rmse"])
                assert math.isfinite(e) and e > 0
                assert (e <= t) == (r["reached"] == "True")
                if r["reached"] == "True":
                    assert int(r["terms"]) >= most or r["monotone"] == "False", (m, t, r)
                    most = max(most, int(r["terms"]))
                assert float(r["bytes_per_vertex"]) > 0
    assert any(r["reached"] == "True" for r in rows)  # the quick targets are reachable by someone
    assert (tmp_path / "terms_vs_exponent.png").stat().st_size > 10_000


def test_palette_one_colour_per_method():
    assert len(set(METHOD_COLORS.values())) == len(METHOD_COLORS)
    assert method_color("ptt_separated") == METHOD_COLORS["ptt"]
    assert method_color("new_method") == method_color("new_method") and method_color("new_method").startswith("#")
    with pytest.raises(ValueError):
        method_color("")


def test_report_embeds_latest_study_figures(tmp_path):
    """reports.html.study_figures: terms-vs-exponent PNGs embedded as data URIs with their CSV
    paths, other studies' PNGs linked relative to the report; nothing when there is no folder."""
    import base64

    import numpy as np
    from matplotlib import image as mpimg

    from reports import html as H

    root = tmp_path / "studies"
    (root / "terms-vs-exponent").mkdir(parents=True)
    (root / "mahajan-fig3a").mkdir()
    png = root / "terms-vs-exponent" / "terms_vs_exponent.png"
    mpimg.imsave(png, np.zeros((4, 4, 3), np.uint8))
    (root / "terms-vs-exponent" / "terms_vs_exponent.csv").write_text("a\n1\n")
    mpimg.imsave(root / "mahajan-fig3a" / "k_vs_s.png", np.zeros((4, 4, 3), np.uint8))
    run = tmp_path / "smoke"
    run.mkdir()
    out = H.study_figures(root, run)
    assert "data:image/png;base64," + base64.b64encode(png.read_bytes()).decode() in out
    assert "terms_vs_exponent.csv" in out
    assert 'href="../studies/mahajan-fig3a/k_vs_s.png"' in out
    assert H.study_figures(tmp_path / "nowhere", run) == ""
    assert H.study_figures(None, run) == ""


def _csv_rows(path, drop=("seconds", "cpu_seconds")):
    return [{k: v for k, v in r.items() if k not in drop} for r in csv.DictReader(open(path))]


def test_parallel_shared_path_equals_plain_path(tmp_path):
    """The CLI's path (2 worker processes of one torch thread, rung-independent precompute pieces
    shared within a search: `methods.base.shared_precompute`) writes the same CSV rows, every number
    as the same string, as the plain path (this process, every precompute from scratch) — only the
    seconds differ. (zh_shadow is left out: its order-3 render is not thread-count independent,
    reports.studies comment above SEARCH_COST_HINT.) The quick
    rungs of the ladders that share pieces (in-out's rule-K regions, PTT's lobe tables and env
    filters, triple product's untruncated V and BRDF tables) and one cheap ladder, two exponents."""
    cfg = S.restrict(S.YARDSTICK_QUICK, methods=["inout", "ptt", "triple_product", "sh_prt"])
    S.terms_vs_exponent(tmp_path / "plain", config=cfg, jobs=1, shared=False)
    S.terms_vs_exponent(tmp_path / "fast", config=cfg, jobs=2, shared=True)
    for name in ("terms_vs_exponent.csv", "ladder_evaluations.csv"):
        plain, fast = _csv_rows(tmp_path / "plain" / name), _csv_rows(tmp_path / "fast" / name)
        assert len(plain) == len(fast) > 0
        assert plain == fast, name
    evals = _csv_rows(tmp_path / "fast" / "ladder_evaluations.csv", drop=())
    assert all(float(e["cpu_seconds"]) > 0 for e in evals)  # measured in the workers


def test_shared_precompute_reuses_pieces_and_keeps_images():
    """One memo over two rungs and two exponents: later precomputes take in-out's rule-K region, PTT's
    lobe fit and env filters and triple product's untruncated tables from it (the same objects), and
    every image and memory() equals a from-scratch one."""
    from methods.base import shared_precompute

    cfg = S.YARDSTICK_QUICK
    frames = [S._phong_frame("sphere_plane", "sphere", s, cfg) for s in (1.0, 16.0)]
    for name in ("inout", "ptt", "triple_product"):
        lad = MS.TERM_LADDERS[name]
        memo: dict = {}
        made = []
        for fr in frames:
            for rung in lad.quick:
                plain = lad.make(dict(rung), "sphere")
                plain.precompute(fr.scene)
                shared = lad.make(dict(rung), "sphere")
                with shared_precompute(memo):
                    shared.precompute(fr.scene)
                assert torch.equal(plain.render(fr.frame, fr.gbuffer), shared.render(fr.frame, fr.gbuffer)), name
                assert plain.memory() == shared.memory()
                made.append(shared)
        assert memo, name
        if name == "inout":  # the plane (Lambert, K by rule) is one object in every precompute
            planes = [next(r for r in m.regions if r.name == "plane") for m in made]
            assert all(p is planes[0] for p in planes)
            assert all(next(r for r in m.regions if r.name == "sphere") is not None for m in made)
        elif name == "ptt":
            assert made[0].env_filters is made[-1].env_filters and made[0].lobe_table is made[1].lobe_table
        else:  # the untruncated visibility (one geometry) and one BRDF table per material
            assert sum(k[0] == "triple_product.vis_coeffs" for k in memo) == 1
            assert sum(k[0] == "triple_product.brdf_table" for k in memo) == 3  # plane, sphere at s = 1, 16


def test_restrict_and_run_study_options(tmp_path):
    cfg = S.restrict(S.YARDSTICK, scenes=["shadow_detail"], exponents=[2, 8], methods=["sh_prt"])
    assert cfg.scenes == (("shadow_detail", "object"),) and cfg.exponents == (2.0, 8.0) and cfg.methods == ("sh_prt",)
    with pytest.raises(ValueError, match="unknown scene"):
        S.restrict(S.YARDSTICK, scenes=["nope"])
    with pytest.raises(ValueError, match="no term ladder"):
        S.restrict(S.YARDSTICK, methods=["nope"])
    with pytest.raises(ValueError, match="jobs"):
        S.yardstick_table(S.YARDSTICK_QUICK, jobs=0)
    with pytest.raises(ValueError, match="takes no option"):
        MS.run_study("terms-own-criteria", tmp_path, quick=True, jobs=2)


def test_measure_option_is_validated_and_restricted():
    assert S.YARDSTICK.measure == "region" and S.YARDSTICK_QUICK.measure == "region"
    assert S.restrict(S.YARDSTICK, measure="image").measure == "image"
    with pytest.raises(ValueError, match="measure"):
        S.YardstickConfig(measure="pixels")
    with pytest.raises(ValueError, match="measure"):
        S.restrict(S.YARDSTICK, measure="pixels")


def test_region_pixels_are_those_seen_by_the_region_alone():
    """On the study's sphere_plane frame: the searched pixels are the covered ones all of whose G-buffer
    sub-samples hit the sphere (counted here per pixel from the samples directly), a strict subset of the
    covered pixels that leaves out the silhouette; the frame's mean and floor are the reference's over them."""
    from references.metrics import rmse

    cfg = S.YARDSTICK_QUICK
    fr = S._phong_frame("sphere_plane", "sphere", 1.0, cfg)
    g = fr.gbuffer
    k = g.spp_side ** 2
    sph = list(fr.scene.regions).index("sphere")
    own = ((g.region == sph) & g.hit).view(g.height, g.width, k)
    want = own.all(-1) & fr.image_mask
    assert torch.equal(fr.mask, want)
    some = own.any(-1) & ~own.all(-1) & fr.image_mask       # silhouette pixels: sphere and plane mixed
    assert int(some.sum()) > 0 and not bool((fr.mask & some).any())
    assert 0 < int(fr.mask.sum()) < int(fr.image_mask.sum())
    assert fr.mean == pytest.approx(float(fr.reference.image[fr.mask].mean()), rel=1e-6)
    ref = fr.reference
    assert fr.floor == pytest.approx(rmse(ref.half_a, ref.half_b, fr.mask) / 2 / fr.mean, rel=1e-6)
    with pytest.raises(ValueError, match="no region"):
        S.region_pixels(g, fr.scene, "teapot", fr.image_mask)
    img = S._phong_frame("sphere_plane", "sphere", 1.0, S.restrict(cfg, measure="image"))
    assert torch.equal(img.mask, fr.image_mask) and img.image_mask is None and img.mean == fr.image_mean


def _split_frame(scene_name, region, s, cfg):
    """4 × 4 pixels, the varied region the right half: `_Split` renders its error on the left half only."""
    full = torch.ones(4, 4, dtype=torch.bool)
    right = torch.zeros(4, 4, dtype=torch.bool)
    right[:, 2:] = True
    if cfg.measure == "image":
        return S._Frame({"s": s}, {"s": s}, None, _Ref(), full, 1.0, 0.001, 10)
    return S._Frame({"s": s}, {"s": s}, None, _Ref(), right, 1.0, 0.001, 10, full, 1.0, 0.002)


def test_search_takes_the_error_over_the_measured_pixels(tmp_path, monkeypatch, clean_ladders):
    """A method whose error lies only outside the varied region (as the ground's per-vertex shadows do, which no
    rung changes): over the region it reaches every target at the first rung, over the image at the rung its curve
    says; both errors are in the CSV either way."""
    monkeypatch.setattr(S, "_phong_frame", _split_frame)
    MS.TERM_LADDERS.clear()

    class _Split(_Fake):
        def render(self, frame, gbuffer):
            img = torch.ones(4, 4, 3)
            img[:, :2] += 0.09 * frame["s"] / self.config["terms"]
            return img

    MS.register_term_ladder("split", [dict(terms=k) for k in range(1, 65)], lambda c, r: _Split(**c), replace=True)
    for measure in ("region", "image"):
        cfg = S.YardstickConfig(scenes=(("a", "r"),), exponents=(1, 4), targets=(0.05,), ref_spp=2, measure=measure)
        S.terms_vs_exponent(tmp_path / measure, config=cfg)
        rows = list(csv.DictReader(open(tmp_path / measure / "terms_vs_exponent.csv")))
        assert len(rows) == 2 and all(r["measure"] == measure for r in rows)
        for r in rows:
            s, k = float(r["exponent"]), int(r["terms"])
            image_err = 0.09 * s / k / math.sqrt(2)                  # half the pixels off by 0.09 s / K
            assert float(r["rel_rmse_image"]) == pytest.approx(image_err, rel=1e-5)
            if measure == "region":
                assert k == 1 and float(r["rel_rmse"]) == 0.0 and float(r["noise_floor_image"]) == 0.002
            else:
                assert k == math.ceil(0.09 * s / math.sqrt(2) / 0.05) and float(r["rel_rmse"]) == float(r["rel_rmse_image"])


def test_scan_ladder_finds_the_smallest_rung_where_the_error_is_not_monotone(tmp_path, monkeypatch, clean_ladders):
    """A ladder whose error grows along it (the SH ladders: a truncated shadowed render's error is a signed tail
    sum): err = 0.5 / k, plus 0.2 from k = 12 on except a dip at 21 <= k <= 26. Targets 0.11 (k = 5; k = 4 reads
    0.125) and 0.03 (k = 21 reads 0.024, k = 20 0.225, the top k = 64 0.208). Scanned: 5 and 21, each with the
    rung below missing. The gallop and bisection of a monotone ladder on the same curve (rungs k = 6, 8, 12, 20,
    36, 64 from the looser target's) miss the dip and call 0.03 unreached, so the test can fail."""
    monkeypatch.setattr(S, "_phong_frame", _fake_frame)
    MS.TERM_LADDERS.clear()
    renders: list = []
    err = lambda s, k: 0.5 / k + (0.2 if k >= 12 and not 21 <= k <= 26 else 0.0)  # noqa: E731
    _ladder("scanned", err, renders, scan=True)
    _ladder("bisected", err, renders, scan=False)
    cfg = S.YardstickConfig(scenes=(("a", "r"),), exponents=(1,), targets=(0.03, 0.11), ref_spp=2)
    S.terms_vs_exponent(tmp_path, config=cfg)
    rows = {(r["method"], float(r["target"])): r for r in csv.DictReader(open(tmp_path / "terms_vs_exponent.csv"))}
    for t, k in {0.11: 5, 0.03: 21}.items():
        r = rows[("scanned", t)]
        assert r["reached"] == "True" and int(r["terms"]) == k and r["search"] == "scan", r
        assert float(r["prev_rel_rmse"]) > t
    b = rows[("bisected", 0.03)]
    assert b["search"] == "bisect" and b["reached"] == "False"
    assert int(rows[("bisected", 0.11)]["terms"]) == 5


def test_sh_ladders_scan():
    assert MS.TERM_LADDERS["zh_shadow"].scan and MS.TERM_LADDERS["sh_prt"].scan
    assert not MS.TERM_LADDERS["inout"].scan
