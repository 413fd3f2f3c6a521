"""Session 36's count correction applied to a perf run made before it (issue 14): every cell's bytes minus
3·P + 12·(P − H·W) (P = 256²·4 samples, H·W = 256² pixels: the hit flag counted as 4 bytes instead of 1,
the output as the (P, 3) per-sample radiance instead of the (H, W, 3) image; `methods.base.output_bytes`),
the efficiency max(bytes' / bw, flops / peak) / t with the run's own limits (bw from the cell: bytes /
(eff · t) when memory-bound; peak from run.json). ZH's lighting-only frames read no hit flag, so for them
the correction is 0.79 MB too large (their recounted efficiency a little low). Prints the tally.

    python -m benchmarks.perf_recount runs/perf-s35 runs/perf-s35b
"""
import json
import sys
import pandas as pd
for run in sys.argv[1:]:
    d = pd.read_parquet(f'{run}/results.parquet')
    pk = json.load(open(f'{run}/run.json'))['matmul_peak']
    key = ['method', 'config', 'scene', 'sequence']
    g = lambda m: d[d.metric == m].set_index(key).value
    e, b, f, t, cb = g('roofline_efficiency'), g('bytes_per_frame'), g('flops_per_frame'), g('render_time_median'), g('roofline_compute_bound')
    P, HW = 256 * 256 * 4, 256 * 256
    corr = 3 * P + 12 * (P - HW)
    n_old = n_new = 0
    for k in e.index:
        if cb[k] == 1:
            new = e[k]
        else:
            bw = b[k] / (e[k] * t[k])
            new = max((b[k] - corr) / bw, f[k] / pk) / t[k]
        n_old += e[k] >= 0.1; n_new += new >= 0.1
    print(run, 'old', n_old, 'recounted', n_new, 'of', len(e))
