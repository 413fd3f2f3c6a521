"""Self-contained HTML report of one run (a single file; images are base64 PNG data URIs, so it
opens from disk with no network and no side files).

Sections: run facts; summary per scene × method (error with noise floor, memory, precompute, fps
per sequence kind, roofline efficiency, equal-error speedup); error–memory–time trade-off plots
(matplotlib); per scene an image comparison (reference / method / error map) with an exposure
slider; the capability matrix with n/a reasons; regressions since the previous run; per-vertex
error on the mesh (pyvista off-screen renders; skipped with the reason if VTK cannot render);
the latest cross-method study figures (``<studies_dir>/terms-vs-exponent/*.png`` embedded, with
their CSV paths; other studies' PNGs linked). Method colours: `reports.palette`.

Exposure slider — honest re-exposure: the linear float radiance is embedded (float16, base64) and
the page re-tonemaps it (× 2^EV, clip, sRGB OETF) into a canvas, instead of brightening 8-bit
pixels with a CSS filter (which would invent detail that clipped). The initial ``<img>`` holds the
EV 0 image rendered by Python with the same tone map, so the report also reads without JS.
"""
from __future__ import annotations

import base64
import html
import io
import json
import math
import os
from pathlib import Path

import numpy as np
import pandas as pd

from reports.cells import MEASURED
from reports.palette import method_color
from reports.regress import CONTENTION_MAX
from scenes.io import atomic_write_text

KIND_ORDER = ["V", "VB", "VBL", "P", "L", "E", "VL"]
# The display exposure maps this percentile of the reference's luminance to white (same rule as
# references.metrics.Exposure).
WHITE_PERCENTILE = 99.0
LUM = np.array([0.2126, 0.7152, 0.0722])  # Rec.709 luminance weights
MAX_EMBED_SIDE = 256  # larger images are box-downsampled before embedding (report size)
# Studies whose PNGs the report embeds (the rest of <studies_dir>/*/*.png is linked).
EMBED_STUDIES = ("terms-vs-exponent",)


# -- small helpers ----------------------------------------------------------------------------


def esc(x) -> str:
    return html.escape(str(x))


def png_data_uri(rgb8: np.ndarray) -> str:
    """(H, W, 3|4) uint8 → ``data:image/png;base64,…`` (matplotlib's PNG writer)."""
    import matplotlib.image as mpimg

    buf = io.BytesIO()
    mpimg.imsave(buf, rgb8, format="png")
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode()


def fig_data_uri(fig) -> str:
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90, bbox_inches="tight")
    plt.close(fig)
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode()


def srgb_oetf(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1.0 / 2.4) - 0.055)


def tonemap(img: np.ndarray, scale: float, ev: float = 0.0) -> np.ndarray:
    """Linear radiance (H, W, 3) → uint8 sRGB: × scale·2^EV, clip, sRGB OETF (what the JS does)."""
    return (srgb_oetf(np.nan_to_num(img, nan=0.0, posinf=0.0) * scale * 2.0**ev) * 255.0 + 0.5).astype(np.uint8)


def auto_scale(ref: np.ndarray, mask: np.ndarray | None = None) -> float:
    lum = ref @ LUM
    v = lum[mask] if mask is not None and mask.any() else lum.reshape(-1)
    w = float(np.percentile(v, WHITE_PERCENTILE)) if v.size else 0.0
    return 1.0 / w if w > 0 else 1.0


def downsample(img: np.ndarray, max_side: int = MAX_EMBED_SIDE) -> np.ndarray:
    H, W = img.shape[:2]
    f = int(math.ceil(max(H, W) / max_side))
    if f <= 1:
        return img
    H2, W2 = H // f, W // f
    return img[: H2 * f, : W2 * f].reshape(H2, f, W2, f, *img.shape[2:]).mean((1, 3))


def f16_b64(img: np.ndarray) -> str:
    return base64.b64encode(np.ascontiguousarray(img, dtype="<f2").tobytes()).decode()


def error_map(img: np.ndarray, ref: np.ndarray, mask: np.ndarray, vmax: float) -> np.ndarray:
    """|img − ref| averaged over RGB, magma colour map on [0, vmax], uncovered pixels grey."""
    import matplotlib

    e = np.abs(np.nan_to_num(img, nan=1e9) - ref).mean(-1)
    rgba = matplotlib.colormaps["magma"](np.clip(e / max(vmax, 1e-30), 0, 1))
    rgb = (rgba[..., :3] * 255 + 0.5).astype(np.uint8)
    rgb[~mask] = 96
    return rgb


def fmt(v, spec: str = ".3g", unit: str = "") -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "–"
    return f"{v:{spec}}{unit}"


def fmt_seconds(t) -> str:
    """A duration: seconds from 1 s up, milliseconds below, "< 1 ms" under a millisecond (a method with
    nothing to precompute, such as the oracle, reads a few µs, not "1.97e-06 s")."""
    if t is None or not math.isfinite(t):
        return "–"
    if t >= 1.0:
        return f"{t:.3g} s"
    return f"{1e3 * t:.3g} ms" if t >= 1e-3 else "< 1 ms"


def fmt_bytes(b) -> str:
    if b is None or not math.isfinite(b):
        return "–"
    for u in ("B", "KiB", "MiB", "GiB"):
        if abs(b) < 1024 or u == "GiB":
            return f"{b:.0f} {u}" if u == "B" else f"{b:.1f} {u}"
        b /= 1024.0
    return "–"


def _val(g: pd.DataFrame, metric: str, frame: int = -1):
    r = g[(g["metric"] == metric) & (g["frame"] == frame)]
    if len(r) == 0:
        return None, None
    return float(r.iloc[0]["value"]), float(r.iloc[0]["noise_floor"])


def _blabel(b: int) -> str:
    return "full" if int(b) == -1 else str(int(b))


# The method every one of the four papers improves on, marked in every table and legend.
BASELINE = {"sh_prt": "baseline: SH PRT, Sloan 2002"}


def _method_label(method: str, config: str) -> str:
    name = f"{method} ({BASELINE[method]})" if method in BASELINE else method
    return name if config in ("{}", "") else f"{name} {config}"


# -- sections ---------------------------------------------------------------------------------


def _fps_cell(g: pd.DataFrame | None) -> str:
    """A summary-table fps cell, shaded when the cell was timed beside other work (``other_cpu_cores``
    above ``regress.CONTENTION_MAX``)."""
    if g is None:
        return "<td>–</td>"
    other = _val(g, "other_cpu_cores")[0]
    text = fmt(_val(g, "fps")[0], ".1f")
    if other is not None and other > CONTENTION_MAX:
        return f"<td class=loaded title='other processes used {other:.2f} cores while timed'>{text}</td>"
    return f"<td>{text}</td>"


def contention_text(df: pd.DataFrame) -> str | None:
    """The header's line on other work during the timed frames: median and max ``other_cpu_cores``
    over the timed cells, and how many exceeded ``regress.CONTENTION_MAX`` (None when no cell has it)."""
    r = df[(df["metric"] == "other_cpu_cores") & (df["frame"] == -1)]
    v = r["value"].to_numpy(dtype=float)
    ok = np.isfinite(v)
    if not ok.any():
        return None
    over = int((v[ok] > CONTENTION_MAX).sum())
    return (f"median {np.median(v[ok]):.2f}, max {v[ok].max():.2f} cores over {int(ok.sum())} timed cells; "
            + (f"{over} above {CONTENTION_MAX:g} (shaded in the summary; their frame times are not compared "
               "with the history)" if over else f"none above {CONTENTION_MAX:g}"))


def cell_limits_text(df: pd.DataFrame) -> str | None:
    """The spread of the limits measured after each timed cell's frames (``host_triad_bandwidth``,
    ``host_matmul_peak``): min, median, max over the cells, or None when no cell has them."""
    parts = []
    for metric, scale, unit in (("host_triad_bandwidth", 1e9, "GB/s"), ("host_matmul_peak", 1e9, "GFLOP/s")):
        v = df[(df["metric"] == metric) & (df["frame"] == -1)]["value"].to_numpy(dtype=float)
        v = v[np.isfinite(v)] / scale
        if len(v):
            parts.append(f"{v.min():.1f} / {np.median(v):.1f} / {v.max():.1f} {unit}")
    if not parts:
        return None
    n = int(((df["metric"] == "host_triad_bandwidth") & (df["frame"] == -1)).sum())
    return f"min / median / max over {n} cells: " + ", ".join(parts)


def _roof_bound(cells) -> str:
    """" (memory)" | " (compute)" | " (traversal)": the bound most of a row's cells are at ("" if none says)."""
    votes = {"memory": 0, "compute": 0, "traversal": 0}
    for gg in cells:
        c, t = _val(gg, "roofline_compute_bound")[0], _val(gg, "roofline_traversal_bound")[0]
        if c is None and t is None:
            continue
        votes["traversal" if t else "compute" if c else "memory"] += 1
    return f" ({max(votes, key=votes.get)})" if any(votes.values()) else ""


def summary_table(df: pd.DataFrame) -> str:
    ok = df[df["status"].isin(MEASURED)]
    if len(ok) == 0:
        return "<p>No cell ran successfully.</p>"
    kinds = [k for k in KIND_ORDER if k in set(ok["sequence"])]
    head = ("<tr><th>scene</th><th>method</th><th>bounces</th><th>RMSE (noise floor)</th><th>FLIP</th>"
            "<th>memory</th><th>peak RSS</th><th>precompute</th>" + "".join(f"<th>fps {k}</th>" for k in kinds)
            + "<th>roofline eff.</th><th>eq.-error speedup</th></tr>")
    body = []
    for (scene, method, config, b), g in ok.groupby(["scene", "method", "config", "bounces"], sort=True):
        cells = {k: gg for k, gg in g.groupby("sequence")}
        first = cells[[k for k in KIND_ORDER if k in cells][0]]
        rm = [(v, f) for k, gg in cells.items() for v, f in [_val(gg, "rmse")] if v is not None]
        rmse = f"{np.mean([v for v, _ in rm]):.4g} ({np.mean([f for _, f in rm]):.2g})" if rm else "–"
        fl = [v for gg in cells.values() for v, _ in [_val(gg, "flip")] if v is not None]
        mem = _val(first, "memory_bytes")[0]
        rss = [v for gg in cells.values() for v, _ in [_val(gg, "peak_rss_bytes")] if v is not None]
        pre = _val(first, "precompute_time")[0]
        fps = "".join(_fps_cell(cells.get(k)) for k in kinds)
        roof = [v for gg in cells.values() for v, _ in [_val(gg, "roofline_efficiency")] if v is not None]
        bound = _roof_bound(cells.values())
        sp = [v for gg in cells.values() for v, _ in [_val(gg, "eq_error_speedup")] if v is not None and math.isfinite(v)]
        body.append(
            f"<tr><td>{esc(scene)}</td><td>{esc(_method_label(method, config))}</td><td>{_blabel(b)}</td>"
            f"<td>{rmse}</td><td>{fmt(np.mean(fl) if fl else None, '.3f')}</td><td>{fmt_bytes(mem)}</td>"
            f"<td>{fmt_bytes(max(rss)) if rss else '–'}</td><td>{fmt_seconds(pre)}</td>{fps}"
            f"<td>{fmt(float(np.median(roof)) if roof else None, '.2%')}{bound if roof else ''}</td>"
            f"<td>{fmt(float(np.median(sp)) if sp else None, '.3g', '×')}</td></tr>")
    note = ("<p class=note>RMSE: mean over sequence kinds and scored frames, against the reference of the "
            "cell's bounce count; in brackets the reference noise floor (an RMSE below it is not resolved). "
            "fps: 1 / median frame time, warm-up frame excluded; each timed frame renders right after the harness "
            "rasterised its G-buffer (Mitsuba), so it starts with caches and the thread pool cooled, as in a "
            "deferred renderer (back to back, with the G-buffers made ahead, short frames read faster: "
            "<code>benchmarks.frame_protocol</code>); <span class=loaded>shaded</span>: other processes "
            f"used more than {CONTENTION_MAX:g} cores while the cell's frames were timed (its time, roofline and "
            "speedup are slower than the code). Roofline efficiency: max(bytes per frame ÷ triad "
            "bandwidth, flops per frame ÷ dense-matmul peak, shadow rays per frame ÷ ray rate) ÷ frame time, every "
            "limit measured in this run (the ray rate per scene: the fastest of the suite's tracers on that scene's "
            "shadow rays from the G-buffer's points; only the oracle traces rays in a frame); in "
            "brackets the bound that applies (the largest term). Equal-error speedup: Mitsuba time to reach the method's RMSE "
            "(RMSE ∝ spp<sup>−1/2</sup> fitted to references at several spp, same thread count) ÷ frame time; Mitsuba's "
            "time is its renders alone, without exporting and loading the scene or compiling kernels (as a method's frame "
            "excludes its precomputation and compilation), so the speedup does not credit a method with Mitsuba's "
            "set-up.</p>")
    return f"<table>{head}{''.join(body)}</table>{note}"


RELIGHT_KINDS = ("V", "L", "E", "VL")
REAL_SCENES = ("bunny", "dragon", "character")  # library scenes under captured probes (scenes/assets)


def relighting_table(df: pd.DataFrame) -> str:
    """What PRT exists for: per scene × method, the error on the lighting-only sequences (L: the env
    map rotates about a tilted axis; E: captured probes swapped each frame) and view + lighting (VL),
    next to view-only (V) — RMSE (× the reference's noise floor) and FLIP, direct lighting."""
    ok = df[df["status"].isin(MEASURED) & (df["frame"] == -1) & (df["bounces"] == 0)]
    kinds = [k for k in RELIGHT_KINDS if k in set(ok["sequence"])]
    if not any(k in kinds for k in ("L", "E", "VL")):
        return "<p>No lighting-only sequence in this run.</p>"
    head = ("<tr><th>scene</th><th>method</th>" + "".join(f"<th>{k}: RMSE (× floor)</th><th>{k}: FLIP</th>" for k in kinds)
            + "</tr>")
    body = []
    for (scene, method, config), g in ok.groupby(["scene", "method", "config"], sort=True):
        tds = []
        for k in kinds:
            gk = g[g["sequence"] == k]
            r = gk[gk["metric"] == "rmse"]
            f = gk[gk["metric"] == "flip"]
            if len(r):
                v, fl = float(r["value"].iloc[0]), float(r["noise_floor"].iloc[0])
                sus = " class=sus" if (gk["status"] == "suspect").any() else ""
                tds.append(f"<td{sus}>{v:.3g} ({v / fl:.1f}×)</td>" if fl > 0 else f"<td{sus}>{v:.3g}</td>")
            else:
                tds.append("<td class=none>·</td>")
            tds.append(f"<td>{float(f['value'].iloc[0]):.3g}</td>" if len(f) else "<td class=none>·</td>")
        body.append(f"<tr><td>{esc(scene)}</td><td>{esc(_method_label(method, config))}</td>{''.join(tds)}</tr>")
    note = ("<p class=note>Mean over each sequence's scored frames. L: fixed view and materials, the env map "
            "rotates about a seeded tilted axis; E: fixed view and materials, a different captured probe every "
            "frame; VL: view and lighting change together. A method whose L/E error is far above its V error "
            "does not relight correctly.</p>")
    return f"<table>{head}{''.join(body)}</table>{note}"


def bounces_table(df: pd.DataFrame) -> str:
    """Sun 2007 Fig. 11 as numbers: for methods scored against full GI too (``rmse_full_gi``), the
    RMSE against the reference of the cell's own bounce count and against full GI, per bounce count
    (mean over sequence kinds). Adding bounces must bring the image closer to full GI."""
    ok = df[df["status"].isin(MEASURED) & (df["frame"] == -1)]
    full = ok[ok["metric"] == "rmse_full_gi"]
    if len(full) == 0:
        return "<p>No cell was scored against full global illumination.</p>"
    bs = sorted({int(b) for b in full["bounces"]})
    head = ("<tr><th>scene</th><th>method</th>" + "".join(
        f"<th>{b} bounce{'s' if b != 1 else ''}: RMSE vs same (floor)</th><th>vs full GI (floor)</th>" for b in bs)
        + "</tr>")
    body = []
    for (scene, method, config), g in full.groupby(["scene", "method", "config"], sort=True):
        tds = []
        for b in bs:
            same = ok[(ok["scene"] == scene) & (ok["method"] == method) & (ok["config"] == config)
                      & (ok["bounces"] == b) & (ok["metric"] == "rmse")]
            fb = g[g["bounces"] == b]
            for part in (same, fb):
                tds.append(f"<td>{part['value'].mean():.4g} ({part['noise_floor'].mean():.2g})</td>"
                           if len(part) else "<td>–</td>")
        body.append(f"<tr><td>{esc(scene)}</td><td>{esc(_method_label(method, config))}</td>{''.join(tds)}</tr>")
    note = ("<p class=note>Sun 2007 Fig. 11: each column pair is one precomputation rendered with that many "
            "indirect bounces; the error against full GI should fall as bounces are added, the error against "
            "the same-bounce reference measures the method's own approximation.</p>")
    return f"<table>{head}{''.join(body)}</table>{note}"


def tradeoff_plots(df: pd.DataFrame) -> str:
    """RMSE vs memory and RMSE vs frame time (one point per ok cell; colour = method)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ok = df[df["status"].isin(MEASURED) & (df["frame"] == -1)]
    pts = []
    for (scene, method, config, seq, b), g in ok.groupby(["scene", "method", "config", "sequence", "bounces"]):
        r, _ = _val(g, "rmse")
        m, _ = _val(g, "memory_bytes")
        t, _ = _val(g, "render_time_median")
        if r is not None:
            pts.append((scene, _method_label(method, config), seq, r, m, t, method))
    if not pts:
        return "<p>No error measurements to plot.</p>"
    methods = sorted({p[1] for p in pts})
    base_of = {p[1]: p[6] for p in pts}
    scenes = sorted({p[0] for p in pts})
    markers = "osD^v<>ph*"
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for ax, idx, xl in ((axes[0], 4, "memory (bytes)"), (axes[1], 5, "median frame time (s)")):
        for i, meth in enumerate(methods):
            for j, sc in enumerate(scenes):
                sel = [p for p in pts if p[1] == meth and p[0] == sc and p[idx] is not None and p[idx] >= 0]
                if sel:
                    ax.scatter([p[idx] for p in sel], [p[3] for p in sel], color=method_color(base_of[meth]),
                               marker=markers[j % len(markers)], label=f"{meth} / {sc}", s=36)
        xs = [p[idx] for p in pts if p[idx] is not None and p[idx] > 0]
        ys = [p[3] for p in pts if p[3] > 0]
        if xs and max(xs) > 10 * min(xs):  # log only where the data spans a decade
            ax.set_xscale("log")
        if ys and max(ys) > 10 * min(ys):
            ax.set_yscale("log")
        ax.set_xlabel(xl)
        ax.set_ylabel("RMSE")
        ax.grid(True, which="both", alpha=0.3)
    axes[1].legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.02, 1.0), frameon=False)
    fig.suptitle("error – memory – time trade-off (one point per cell; colour = method, marker = scene)")
    return f'<img class=plot alt="trade-off plot" src="{fig_data_uri(fig)}">'


def study_figures(studies_dir: str | os.PathLike | None, report_dir: Path) -> str:
    """The latest study outputs under ``studies_dir`` (``out/studies`` by default): the PNGs of
    ``EMBED_STUDIES`` as data URIs with their CSV paths, every other study's PNGs as relative
    links. "" if there is no such folder."""
    if studies_dir is None or not Path(studies_dir).is_dir():
        return ""
    root = Path(studies_dir)
    parts = []
    for name in EMBED_STUDIES:
        d = root / name
        pngs = sorted(d.glob("*.png")) if d.is_dir() else []
        if not pngs:
            continue
        csvs = ", ".join(f"<code>{esc(p)}</code>" for p in sorted(d.glob("*.csv")))
        figs = "".join(f'<figure><img class=plot alt="{esc(p.name)}" src="data:image/png;base64,'
                       f'{base64.b64encode(p.read_bytes()).decode()}"><figcaption>{esc(p)}</figcaption></figure>'
                       for p in pngs)
        parts.append(f"<h3>{esc(name)}</h3><p class=note>run_bench.py study {esc(name)}; data: {csvs or 'no CSV'}</p>{figs}")
    links = []
    for d in sorted(p for p in root.iterdir() if p.is_dir() and p.name not in EMBED_STUDIES):
        for png in sorted(d.glob("*.png")):
            links.append(f'<a href="{esc(os.path.relpath(png, report_dir))}">{esc(d.name)}/{esc(png.name)}</a>')
    if links:
        parts.append(f"<p>Other study figures: {' · '.join(links)}</p>")
    if not parts:
        return ""
    return "<h2 id=studies>Study figures (latest)</h2>" + "".join(parts)


def capability_matrix(df: pd.DataFrame) -> str:
    cells = df.drop_duplicates("cell")
    cols = sorted({(s, int(b)) for s, b in zip(cells["sequence"], cells["bounces"])},
                  key=lambda x: (KIND_ORDER.index(x[0]) if x[0] in KIND_ORDER else 9, x[1] if x[1] >= 0 else 99))
    head = "<tr><th>scene</th><th>method</th>" + "".join(f"<th>{esc(s)}, b={_blabel(b)}</th>" for s, b in cols) + "</tr>"
    body = []
    for (scene, method, config), g in cells.groupby(["scene", "method", "config"], sort=True):
        tds = []
        for s, b in cols:
            r = g[(g["sequence"] == s) & (g["bounces"] == b)]
            if len(r) == 0:
                tds.append("<td class=none>·</td>")
                continue
            st, reason = r.iloc[0]["status"], r.iloc[0]["reason"]
            if st == "ok":
                tds.append("<td class=ok>✓</td>")
            elif st == "suspect":
                tds.append(f"<td class=sus title='{esc(reason)}'>suspect: {esc(str(reason)[:80])}</td>")
            elif st == "na":
                tds.append(f"<td class=na>n/a: {esc(reason)}</td>")
            else:
                tds.append(f"<td class=err title='{esc(reason)}'>error: {esc(str(reason)[:80])}</td>")
        body.append(f"<tr><td>{esc(scene)}</td><td>{esc(_method_label(method, config))}</td>{''.join(tds)}</tr>")
    return f"<table class=matrix>{head}{''.join(body)}</table>"


def executor_summary(prov: list[dict] | None) -> str:
    """One line per (executor, workers, threads, part): how many cells' numbers it produced (plain
    text; the caller escapes it)."""
    if not prov:
        return "?"
    counts: dict[tuple, int] = {}
    for p in prov:
        k = (p.get("executor", "?"), p.get("workers", "?"), p.get("threads", "?"), p.get("part", "all"))
        counts[k] = counts.get(k, 0) + 1
    what = {"all": "all numbers", "errors": "image errors", "timing": "timings (one at a time per machine)"}
    return "; ".join(f"{e} ({w} worker{'s' if w != 1 else ''}, {t} thread{'s' if t != 1 else ''} "
                     f"per task): {what.get(part, part)} of {n} cell{'s' if n != 1 else ''}"
                     for (e, w, t, part), n in sorted(counts.items(), key=lambda kv: str(kv[0])))


def provenance_table(prov: list[dict] | None) -> str:
    """Which executor, workers, host and threads produced each cell's numbers."""
    if not prov:
        return "<p>Not recorded.</p>"
    cols = ["method", "scene", "sequence", "bounces", "part", "executor", "workers", "threads", "host", "worker",
            "code", "status"]
    head = "<tr>" + "".join(f"<th>{c}</th>" for c in cols) + "</tr>"
    body = "".join("<tr>" + "".join(f"<td>{esc(_blabel(p[c]) if c == 'bounces' else p.get(c, ''))}</td>"
                                    for c in cols) + "</tr>" for p in prov)
    return f"<table class=prov>{head}{body}</table>"


def regressions_section(changes: pd.DataFrame | None, prev_run: str | None) -> str:
    if changes is None or prev_run is None:
        return "<p>No previous run in the history: nothing to compare with.</p>"
    fl = changes[changes["flag"] != ""]
    intro = f"<p>Compared with run <code>{esc(prev_run)}</code>: {len(changes)} values compared, " \
            f"{int((fl['flag'] == 'regression').sum())} regression(s), {int((fl['flag'] == 'improvement').sum())} improvement(s).</p>"
    if len(fl) == 0:
        return intro
    rows = []
    for _, r in fl.iterrows():
        cls = "reg" if r["flag"] == "regression" else "imp"
        rc = f"{100 * r['rel_change']:+.1f}%" if math.isfinite(r["rel_change"]) else "–"
        pv = f"{r['p_value']:.1e}" if math.isfinite(r["p_value"]) else "–"
        rows.append(f"<tr class={cls}><td>{esc(r['flag'])}</td><td>{esc(r['scene'])}</td><td>{esc(r['sequence'])}</td>"
                    f"<td>{esc(_method_label(r['method'], r['config']))}</td><td>{_blabel(r['bounces'])}</td>"
                    f"<td>{esc(r['metric'])}</td><td>{fmt(r['old'], '.4g')}</td><td>{fmt(r['new'], '.4g')}</td>"
                    f"<td>{rc}</td><td>{pv}</td><td>{esc(r['test'])}</td></tr>")
    head = ("<tr><th>flag</th><th>scene</th><th>seq</th><th>method</th><th>b</th><th>metric</th><th>old</th>"
            "<th>new</th><th>change</th><th>p</th><th>test</th></tr>")
    return intro + f"<table>{head}{''.join(rows)}</table>"


def _load_images(out_dir: Path, df: pd.DataFrame) -> dict:
    """(scene, sequence, bounces) → list of (method label, arrays) from the cells' npz files."""
    art = {}
    ok = df[df["status"].isin(MEASURED)].drop_duplicates("cell")
    for _, r in ok.iterrows():
        p = out_dir / "images" / f"{r['cell']}.npz"
        if not p.exists():
            continue
        with np.load(p) as z:
            arrays = {k: z[k] for k in z.files}
        art.setdefault((r["scene"], r["sequence"], int(r["bounces"])), []).append((_method_label(r["method"], r["config"]), arrays))
    return art


def _pick_comparisons(art: dict) -> list[tuple]:
    """One comparison per scene: bounces 0 if present, then the sequence kind most methods ran,
    then the most dynamic kind."""
    by_scene: dict[str, tuple] = {}
    for key in art:
        scene, seq, b = key
        rank = (0 if b == 0 else 1, -len(art[key]), -(KIND_ORDER.index(seq) if seq in KIND_ORDER else -1))
        if scene not in by_scene or rank < by_scene[scene][0]:
            by_scene[scene] = (rank, key)
    return [by_scene[s][1] for s in sorted(by_scene)]


def image_comparisons(art: dict) -> str:
    parts = []
    for n, key in enumerate(_pick_comparisons(art)):
        scene, seq, b = key
        entries = sorted(art[key], key=lambda e: e[0])
        ref = downsample(entries[0][1]["reference"].astype(np.float32))
        mask = downsample(entries[0][1]["mask"].astype(np.float32)) > 0.5
        scale = auto_scale(ref, mask)
        imgs = [downsample(a["method"].astype(np.float32)) for _, a in entries]
        errs = [np.abs(np.nan_to_num(i, nan=0) - ref).mean(-1)[mask] for i in imgs]
        allerr = np.concatenate(errs) if errs else np.zeros(1)
        vmax = float(np.percentile(allerr, 99)) if allerr.size else 1.0
        vmax = vmax if vmax > 0 else 1.0
        H, W = ref.shape[:2]
        figs = [("reference", ref)] + [(lab, im) for (lab, _), im in zip(entries, imgs)]
        tiles = []
        for j, (lab, im) in enumerate(figs):
            iid = f"cmp{n}_{j}"
            tiles.append(f'<figure><img class="hdr" id="{iid}" data-w="{W}" data-h="{H}" data-f16="{f16_b64(im)}" '
                         f'src="{png_data_uri(tonemap(im, scale))}" alt="{esc(lab)}"><figcaption>{esc(lab)}</figcaption></figure>')
        for (lab, _), im in zip(entries, imgs):
            tiles.append(f'<figure><img class="errmap" src="{png_data_uri(error_map(im, ref, mask, vmax))}" '
                         f'alt="error {esc(lab)}"><figcaption>|error| {esc(lab)}</figcaption></figure>')
        frame = int(entries[0][1].get("frame", -1))
        parts.append(
            f'<div class=cmp data-scale="{scale:.6g}"><h3>{esc(scene)} — sequence {esc(seq)}, bounces {_blabel(b)}, frame {frame}</h3>'
            f'<label>exposure <input type=range class=ev min=-8 max=8 step=0.25 value=0> '
            f'<span class=evv>0 EV</span></label> <span class=note>(relative to the auto exposure: '
            f'{WHITE_PERCENTILE:g}th-percentile reference luminance → white; re-tonemapped from the linear data)</span>'
            f'<div class=tiles>{"".join(tiles)}</div>'
            f'<p class=note>Error maps: |method − reference| averaged over RGB, magma colour map on [0, {vmax:.3g}] '
            f'(99th percentile of this scene\'s errors); grey = not covered.</p></div>')
    return "".join(parts) or "<p>No images were saved.</p>"


def probe_strip(out_dir: Path | None, df: pd.DataFrame) -> str:
    """One E sequence as pictures: a row per frame (a different captured probe each), the reference
    and every method side by side, one exposure per row (from its reference)."""
    if out_dir is None:
        return ""
    ok = df[df["status"].isin(MEASURED) & (df["sequence"] == "E") & (df["bounces"] == 0)].drop_duplicates("cell")
    if len(ok) == 0:
        return "<p>No E sequence in this run.</p>"
    # one scene: the one with a captured probe of its own when there is one (in the smoke suite the
    # bunny scan under "sunrise"), else the first by name
    scenes = sorted(set(ok["scene"]))
    scene = next((s for s in scenes if s in REAL_SCENES), scenes[0])
    cols = []
    for _, r in ok[ok["scene"] == scene].sort_values(["method", "config"]).iterrows():
        p = out_dir / "images" / f"{r['cell']}.frames.npz"
        if p.exists():
            with np.load(p) as z:
                cols.append((_method_label(r["method"], r["config"]), {k: z[k] for k in z.files}))
    if not cols:
        return "<p>No E-sequence images were saved.</p>"
    rows = []
    for i in cols[0][1]["frames"].tolist():
        ref = downsample(cols[0][1][f"reference_{i}"].astype(np.float32))
        mask = downsample(cols[0][1][f"mask_{i}"].astype(np.float32)) > 0.5
        scale = auto_scale(ref, mask)
        tiles = [("reference", ref)] + [(lab, downsample(a[f"method_{i}"].astype(np.float32))) for lab, a in cols
                                        if f"method_{i}" in a]
        rows.append(f"<tr><th>frame {i}</th>" + "".join(
            f'<td><img src="{png_data_uri(tonemap(im, scale))}" alt="{esc(lab)} frame {i}"></td>' for lab, im in tiles)
            + "</tr>")
    head = "<tr><th></th><th>reference</th>" + "".join(f"<th>{esc(lab)}</th>" for lab, _ in cols) + "</tr>"
    return (f"<h3>{esc(scene)} — sequence E (frame 0: the scene's probe; then one captured probe per frame)</h3>"
            f"<table class=strip>{head}{''.join(rows)}</table>")


def vertex_error_renders(art: dict, *, window: int = 260) -> str:
    """Per-vertex squared error on the mesh, rendered off-screen with pyvista."""
    try:
        import pyvista as pv

        pv.OFF_SCREEN = True
        try:  # without an X display VTK logs "bad X server connection" at WARN, then renders off-screen (EGL / OSMesa)
            from vtkmodules.vtkCommonCore import vtkLogger

            vtkLogger.SetStderrVerbosity(vtkLogger.VERBOSITY_ERROR)
        except Exception:  # pragma: no cover - a VTK without vtkLogger: its warning stays in the log
            pass
    except Exception as e:  # pragma: no cover - pyvista missing
        return f"<p>Per-vertex error skipped: pyvista unavailable ({esc(e)}).</p>"
    parts = []
    for key in _pick_comparisons(art):
        scene, seq, b = key
        entries = sorted(art[key], key=lambda e: e[0])
        vals = np.concatenate([a["vertex_sq_error"] for _, a in entries])
        vals = vals[np.isfinite(vals)]
        vmax = float(np.percentile(vals, 99)) if vals.size else 1.0
        figs = []
        for lab, a in entries:
            V, F, e = a["V"], a["F"], a["vertex_sq_error"]
            try:
                faces = np.hstack([np.full((len(F), 1), 3), F]).astype(np.int64).ravel()
                mesh = pv.PolyData(V.astype(np.float64), faces)
                mesh.point_data["sq_error"] = e.astype(np.float64)
                size = (window, window)
                if "camera" in a:
                    size = (window, max(16, int(round(window * a["camera"][11] / a["camera"][10]))))
                p = pv.Plotter(off_screen=True, window_size=size)
                p.add_mesh(mesh, scalars="sq_error", cmap="magma", clim=(0, max(vmax, 1e-30)), nan_color="grey",
                           show_scalar_bar=False)
                if "camera" in a:  # the frame's own camera (fov along x → vertical angle for VTK)
                    c = a["camera"]
                    p.camera_position = [tuple(c[0:3]), tuple(c[3:6]), tuple(c[6:9])]
                    aspect = c[11] / c[10]
                    p.camera.view_angle = float(np.degrees(2 * np.arctan(np.tan(np.radians(c[9]) / 2) * aspect)))
                else:
                    p.view_isometric()
                img = p.screenshot(return_img=True)
                p.close()
            except Exception as ex:  # VTK without an off-screen context
                return f"<p>Per-vertex error skipped: pyvista off-screen rendering failed ({esc(type(ex).__name__)}: {esc(ex)}).</p>"
            figs.append(f'<figure><img class=vtx src="{png_data_uri(np.asarray(img, dtype=np.uint8))}" alt="vertex error {esc(lab)}">'
                        f"<figcaption>{esc(lab)}</figcaption></figure>")
        parts.append(f"<h3>{esc(scene)} — sequence {esc(seq)}, bounces {_blabel(b)}</h3><div class=tiles>{''.join(figs)}</div>"
                     f"<p class=note>Each G-buffer sample carries its pixel's squared error (mean over RGB), splatted onto "
                     f"its triangle's vertices with its barycentric weights; magma on [0, {vmax:.3g}]; grey = seen by no scored sample; seen from the frame's camera.</p>")
    return "".join(parts) or "<p>No per-vertex errors were saved.</p>"


_CSS = """
body{font-family:system-ui,sans-serif;margin:1.5em;color:#222;max-width:1400px}
table{border-collapse:collapse;margin:.5em 0;font-size:13px}
td,th{border:1px solid #ccc;padding:3px 6px;text-align:left;vertical-align:top}
th{background:#f0f0f0}.ok{background:#e6f5e6}.na{background:#f3f3f3;color:#666}.err{background:#fbe0e0}.sus{background:#fff0c8}.loaded{background:#e8e0f5}
tr.reg{background:#fbe0e0}tr.imp{background:#e6f5e6}.note{color:#666;font-size:12px}
.tiles{display:flex;flex-wrap:wrap;gap:8px}figure{margin:0}figure img{width:200px;image-rendering:pixelated}
img.plot{max-width:100%}figcaption{font-size:12px;text-align:center}code{background:#f4f4f4}
"""

_JS = r"""
(function(){
function h2f(h){var s=(h&0x8000)?-1:1,e=(h>>10)&31,f=h&1023;
 if(e===0)return s*Math.pow(2,-14)*(f/1024); if(e===31)return f?NaN:s*Infinity;
 return s*Math.pow(2,e-15)*(1+f/1024);}
function oetf(x){x=x<0?0:(x>1?1:x);return x<=0.0031308?12.92*x:1.055*Math.pow(x,1/2.4)-0.055;}
function decode(img){if(img._lin)return img._lin;var bin=atob(img.dataset.f16),n=bin.length/2,
 out=new Float32Array(n);for(var i=0;i<n;i++){out[i]=h2f(bin.charCodeAt(2*i)|(bin.charCodeAt(2*i+1)<<8));}
 img._lin=out;return out;}
function render(img,k){var w=+img.dataset.w,h=+img.dataset.h,lin=decode(img);
 var c=document.createElement('canvas');c.width=w;c.height=h;var ctx=c.getContext('2d');
 var im=ctx.createImageData(w,h);for(var p=0;p<w*h;p++){for(var ch=0;ch<3;ch++){var v=lin[3*p+ch];
 im.data[4*p+ch]=Math.round(255*oetf(isFinite(v)?v*k:0));}im.data[4*p+3]=255;}
 ctx.putImageData(im,0,0);img.src=c.toDataURL('image/png');}
document.querySelectorAll('div.cmp').forEach(function(div){var s=+div.dataset.scale;
 var sl=div.querySelector('input.ev'),lab=div.querySelector('.evv');
 sl.addEventListener('input',function(){var ev=+sl.value;lab.textContent=ev+' EV';
 div.querySelectorAll('img.hdr').forEach(function(img){render(img,s*Math.pow(2,ev));});});});
// "report.html#ev=2" opens at +2 EV (used by the headless-browser test of the re-tonemapping)
var m=location.hash.match(/ev=(-?[0-9.]+)/);
if(m){document.querySelectorAll('input.ev').forEach(function(sl){sl.value=m[1];
 sl.dispatchEvent(new Event('input'));});}
})();
"""


def wall_time_text(meta: dict) -> str | None:
    """'42.0 min' (one invocation) or '42.0 min (2 invocations: 30.0 + 12.0 min)', or None."""
    inv = meta.get("invocations") or []
    if not inv:
        return None
    mins = [float(i.get("seconds", 0.0)) / 60 for i in inv]
    text = f"{sum(mins):.1f} min"
    if len(mins) > 1:
        text += f" ({len(mins)} invocations: {' + '.join(f'{m:.1f}' for m in mins)} min)"
    return text


def build_report(df: pd.DataFrame, out_path: str | os.PathLike, *, run_dir: str | os.PathLike | None = None,
                 meta: dict | None = None, changes: pd.DataFrame | None = None, prev_run: str | None = None,
                 vertex_renders: bool = True, studies_dir: str | os.PathLike | None = None) -> Path:
    """Write the HTML report of run table ``df`` (``reports.store.COLUMNS``) to ``out_path``.

    run_dir: where the cells' ``images/*.npz`` are (default: the report's folder).
    studies_dir: where ``run_bench.py study`` wrote its folders (default: ``<run_dir>/../studies``,
        i.e. ``out/studies`` for a run in ``out/<suite>``); the latest figures are shown if present.
    """
    out_path = Path(out_path)
    run_dir = Path(run_dir) if run_dir is not None else out_path.parent
    meta = dict(meta or {})
    run_rows = df[df["status"] == "run"]
    df = df[df["status"] != "run"]
    art = _load_images(run_dir, df)
    if studies_dir is None:
        studies_dir = run_dir.resolve().parent / "studies"
    first = df.iloc[0] if len(df) else None
    facts = {
        "run": meta.get("run_id", first["run_id"] if first is not None else "?"),
        "suite": meta.get("suite", "?"), "time (UTC)": meta.get("time", first["time"] if first is not None else "?"),
        "git": meta.get("git_sha", first["git_sha"] if first is not None else "?"),
        "machine": meta.get("machine", first["machine"] if first is not None else "?"),
        "threads": meta.get("threads", first["threads"] if first is not None else "?"),
    }
    if meta.get("openmp"):
        facts["OpenMP"] = meta["openmp"]
    if meta.get("provenance"):
        facts["executor"] = executor_summary(meta["provenance"])
    wall = wall_time_text(meta)
    if wall:
        facts["wall time"] = wall + " (references and cells; not this report)"
    busy = contention_text(df)
    if busy:
        facts["other CPU while timing"] = busy
    bw = run_rows[run_rows["metric"] == "triad_bandwidth"]
    if len(bw):
        facts["triad bandwidth"] = f"{float(bw.iloc[0]['value']) / 1e9:.2f} GB/s"
    peak = meta.get("matmul_peak")
    if isinstance(peak, (int, float)) and math.isfinite(peak):
        facts["dense-matmul peak"] = f"{peak / 1e9:.1f} GFLOP/s"
    samples = meta.get("limit_samples") or []
    host = cell_limits_text(df)
    if len(samples) > 1 or host:
        facts["machine limits"] = (f"best of {len(samples)} run measurements (" + "; ".join(
            f"{s.get('when') or '?'}: {s['triad_bandwidth'] / 1e9:.1f} GB/s, {s['matmul_peak'] / 1e9:.0f} GFLOP/s"
            for s in samples) + ")" + (f" and one after each timed cell's frames ({host})" if host else "")
            + "; the roofline uses the best, so a load that slowed one of them does not inflate the efficiencies")
    n_ok, n_na, n_err, n_sus = (int((df.drop_duplicates('cell')["status"] == s).sum())
                                for s in ("ok", "na", "error", "suspect"))
    facts["cells"] = f"{n_ok} ok, {n_sus} suspect, {n_na} n/a, {n_err} failed"
    if first is not None:
        facts["versions"] = ", ".join(f"{k} {v}" for k, v in json.loads(first["versions"] or "{}").items())
    fact_html = "".join(f"<tr><th>{esc(k)}</th><td>{esc(v)}</td></tr>" for k, v in facts.items())
    errors = df[df["status"] == "error"].drop_duplicates("cell")
    err_html = "".join(f"<li><code>{esc(r['cell'])}</code>: {esc(r['reason'])}</li>" for _, r in errors.iterrows())
    suspects = df[df["status"] == "suspect"].drop_duplicates("cell")
    sus_html = "".join(f"<li><code>{esc(r['cell'])}</code>: {esc(r['reason'])}</li>" for _, r in suspects.iterrows())
    body = f"""<!DOCTYPE html>
<html lang=en><head><meta charset="utf-8"><title>prtbench report {esc(facts['run'])}</title>
<style>{_CSS}</style></head><body>
<h1>prtbench report</h1>
<table class=facts>{fact_html}</table>
{f'<h2>Failed cells</h2><ul>{err_html}</ul>' if err_html else ''}
{f'<h2>Suspect cells</h2><p>Measured, but the sanity gate (reports/gate.py) found the image plainly wrong: a material region far from the reference mean, or negative radiance. Their numbers stay in the tables.</p><ul>{sus_html}</ul>' if sus_html else ''}
<h2 id=summary>Summary per scene × method</h2>{summary_table(df)}
<h2 id=relighting>Relighting: lighting-only sequences next to view-only</h2>{relighting_table(df)}
{probe_strip(Path(run_dir) if run_dir is not None else None, df)}
<h2 id=bounces>Interreflection: error vs bounces (Sun 2007 Fig. 11)</h2>{bounces_table(df)}
<h2 id=tradeoff>Error – memory – time</h2>{tradeoff_plots(df)}
{study_figures(studies_dir, out_path.resolve().parent)}
<h2 id=images>Images</h2>{image_comparisons(art)}
<h2 id=matrix>Capability matrix</h2>{capability_matrix(df)}
<h2 id=regressions>Regressions since the last run</h2>{regressions_section(changes, prev_run)}
<h2 id=provenance>Where the numbers come from</h2>{provenance_table(meta.get("provenance"))}
<h2 id=vertex>Per-vertex error on the mesh</h2>{vertex_error_renders(art) if vertex_renders else '<p>Skipped.</p>'}
<script>{_JS}</script>
</body></html>
"""
    return Path(atomic_write_text(out_path, body))
