"""reports.html: the self-contained report of a tiny fake run, checked in headless Chromium
(loads from disk, images/plots present as data URIs, JS re-exposure matches the Python tone map,
screenshot not blank)."""
import base64
import io
import re
import shutil
import subprocess

import numpy as np
import pytest

from reports import html as H
from reports.pipeline import run_suite
from reports.suites import Suite

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
# JS decodes float16 and rounds; Python tone-maps float32: at most 2 of 255 levels apart.
TONEMAP_ATOL = 2
# A rendered report page has text, tables and images: far from a uniform screenshot.
MIN_SCREENSHOT_STD = 10.0

SUITE = Suite(name="smoke", size="test", kinds=("V", "VBL"), n_frames=3, ref_spp=16, spp_side=1,
              scenes=("fake_plane",), eq_err_spp=(8, 32), isolate=False)


@pytest.fixture(scope="module")
def fake_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("run")
    res = run_suite(SUITE, out, methods=["fake", "fake_gi", "fake_fail"], history=out / "hist.parquet",
                    backend="testing.fakes", plugins=("testing.fakes",), progress=False, bandwidth_elements=1 << 16)
    return res


def _chromium(args, tmp_path, timeout=90):
    if not shutil.which(CHROMIUM):
        pytest.skip("chromium not installed (scripts/setup.sh installs it)")
    cmd = [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
           "--disable-background-networking", "--disable-component-update", "--disable-sync",
           f"--user-data-dir={tmp_path / 'chromium-profile'}", *args]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)


def _png(uri: str) -> np.ndarray:
    import matplotlib.image as mpimg

    assert uri.startswith("data:image/png;base64,")
    img = mpimg.imread(io.BytesIO(base64.b64decode(uri.split(",", 1)[1])), format="png")
    return np.round(np.asarray(img)[..., :3] * 255).astype(int)


def test_report_sections_without_browser(fake_run):
    text = fake_run.report.read_text()
    assert fake_run.n_ok == 3 and fake_run.n_error == 1 and fake_run.n_na == 2
    assert "n/a: BRDFs fixed at precompute" in text  # capability matrix reason
    assert "planted failure" in text
    assert "No previous run" in text
    sec = text.split("<h2 id=bounces>", 1)[1].split("<h2 id=tradeoff>", 1)[0]  # Sun 2007 Fig. 11 table
    assert "<td>fake_gi</td>" in sec and "<td>fake</td>" not in sec  # only methods scored against full GI
    assert "http://" not in text and "https://" not in text  # nothing fetched from the network


def test_report_in_headless_chromium(fake_run, tmp_path):
    ev = 2.0
    url = fake_run.report.resolve().as_uri() + f"#ev={ev:g}"
    dom = _chromium(["--dump-dom", url], tmp_path)
    assert dom.returncode == 0, dom.stderr[-2000:]
    html = dom.stdout
    assert "prtbench report" in html and "Capability matrix" in html
    imgs = re.findall(r"<img[^>]*>", html)
    srcs = [re.search(r'src="([^"]+)"', t).group(1) for t in imgs]
    assert all(s.startswith("data:image/png;base64,") for s in srcs)
    classes = [re.search(r'class="?([\w-]+)', t).group(1) for t in imgs]
    # reference + 2 methods (exposure-adjustable), 2 error maps, 1 trade-off plot, 2 vertex renders
    assert classes.count("hdr") == 3 and classes.count("errmap") == 2 and classes.count("plot") == 1
    assert classes.count("vtx") == 2 and "Per-vertex error skipped" not in html
    # the slider's JS re-tonemapped the embedded linear data at +2 EV, exactly like tonemap()
    with np.load(next((fake_run.out_dir / "images").glob("fake_plane-test-V-fake-b0-*.npz"))) as z:
        ref, mask = z["reference"], z["mask"]
    scale = H.auto_scale(ref, mask)
    js_ref = _png(srcs[classes.index("hdr")])
    assert np.abs(js_ref - H.tonemap(ref, scale, ev).astype(int)).max() <= TONEMAP_ATOL
    assert np.abs(js_ref - H.tonemap(ref, scale, 0.0).astype(int)).max() > TONEMAP_ATOL  # it did change

    shot = tmp_path / "shot.png"
    r = _chromium([f"--screenshot={shot}", "--window-size=1200,1600", fake_run.report.resolve().as_uri()], tmp_path)
    assert r.returncode == 0 and shot.exists(), r.stderr[-2000:]
    import matplotlib.image as mpimg

    px = mpimg.imread(shot)
    assert px.std() * 255 > MIN_SCREENSHOT_STD


def test_relighting_table_and_probe_strip(tmp_path):
    """A run with lighting-only sequences gets the relighting table (L and E next to V, RMSE in
    units of the noise floor) and the E sequence's image strip (one row per frame/probe)."""
    suite = Suite(name="relight", size="test", kinds=("V", "L", "E"), n_frames=3, ref_spp=16, spp_side=1,
                  scenes=("fake_plane",), isolate=False)
    res = run_suite(suite, tmp_path, methods=["fake"], history=tmp_path / "hist.parquet", backend="testing.fakes",
                    plugins=("testing.fakes",), progress=False, bandwidth_elements=1 << 16)
    text = res.report.read_text()
    sec = text.split("<h2 id=relighting>", 1)[1].split("<h2 id=bounces>", 1)[0]
    assert "<th>L: RMSE (× floor)</th>" in sec and "<th>E: RMSE (× floor)</th>" in sec and "<th>V: FLIP</th>" in sec
    assert "sequence E" in sec
    strip = sec.split("<table class=strip>", 1)[1].split("</table>", 1)[0]
    assert strip.count("<tr><th>frame ") == 3 and strip.count("data:image/png;base64,") == 6  # ref + fake per frame


def test_cells_timed_beside_other_work_are_shaded_and_counted():
    """The summary shades the fps of a cell whose frames were timed while the rest of the machine used
    more than CONTENTION_MAX cores, and the header counts them; a quiet or unknown cell is plain."""
    from reports import store
    from reports.regress import CONTENTION_MAX

    base = {"run_id": "r", "time": "t", "git_sha": "x", "versions": "{}", "machine": "m", "threads": 2,
            "size": "test", "scene": "chess", "method": "fake", "config": "{}", "bounces": 0, "status": "ok",
            "reason": "", "frame": -1}
    rows = []
    for kind, fps, other in (("V", 100.0, 0.01), ("L", 50.0, 1.3), ("E", 25.0, float("nan"))):
        ident = {**base, "sequence": kind, "cell": f"chess-{kind}"}
        rows += [{**ident, "metric": "fps", "value": fps, "unit": "1/s"},
                 {**ident, "metric": "rmse", "value": 0.1, "unit": "radiance", "noise_floor": 0.01},
                 {**ident, "metric": "other_cpu_cores", "value": other, "unit": "cores"}]
    df = store.to_frame(rows)
    table = H.summary_table(df)
    assert re.search(r"<td class=loaded title='other processes used 1\.30 cores while timed'>50\.0</td>", table)
    assert "<td>100.0</td>" in table and "<td>25.0</td>" in table
    assert table.count("class=loaded title") == 1
    text = H.contention_text(df)
    assert text.startswith("median 0.66, max 1.30 cores over 2 timed cells; 1 above")
    df = df[~((df.metric == "other_cpu_cores") & (df.sequence == "L"))]
    assert H.contention_text(df).endswith(f"none above {CONTENTION_MAX:g}")
    assert H.contention_text(df[df.metric != "other_cpu_cores"]) is None


def test_vertex_renders_without_a_display_log_no_vtk_warning(tmp_path):
    """On a machine without X (CI, this VM) VTK logs "bad X server connection. DISPLAY=" at WARN before it renders
    off-screen: one alarming line at the end of every run. The renders must still come out, and the line must not."""
    import os
    import sys
    from pathlib import Path

    code = ("import numpy as np\n"
            "from reports import html as H\n"
            "V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=np.float32)\n"
            "F = np.array([[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]], dtype=np.int64)\n"
            "art = {('s', 'V', 0): [('m', {'V': V, 'F': F, 'vertex_sq_error': np.arange(4, dtype=np.float32)})]}\n"
            "print('VTX', H.vertex_error_renders(art, window=32).count('class=vtx'))\n")
    env = {k: v for k, v in os.environ.items() if k != "DISPLAY"}
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, env=env,
                       cwd=Path(__file__).resolve().parents[2])
    assert r.returncode == 0, r.stderr[-2000:]
    assert "VTX 1" in r.stdout, (r.stdout, r.stderr[-2000:])
    assert "bad X server" not in r.stderr and "WARN" not in r.stderr, r.stderr[-2000:]


def test_durations_read_in_seconds_milliseconds_or_under_a_millisecond():
    """The summary's precompute column: no exponent notation for a method with (almost) nothing to precompute."""
    assert H.fmt_seconds(17.2179) == "17.2 s"
    assert H.fmt_seconds(1.0) == "1 s"
    assert H.fmt_seconds(0.0123) == "12.3 ms"
    assert H.fmt_seconds(1e-3) == "1 ms"
    assert H.fmt_seconds(1.97e-06) == "< 1 ms"
    assert H.fmt_seconds(None) == "–"
    assert H.fmt_seconds(float("nan")) == "–"
