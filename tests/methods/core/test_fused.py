"""methods.core.fused: compiled blocks equal the eager function; padding, tuples, the off switch."""
from __future__ import annotations

import pytest
import torch

from methods.core.fused import call_rows, fused, map_rows
from methods.core.threads import torch_threads


def _resolve(vidx, bw, col):
    return (col[vidx.long()] * bw[..., None]).sum(1)


def _pair(x, s):
    return x * s, x.sum(1, keepdim=True)


@pytest.fixture(scope="module")
def data():
    g = torch.Generator().manual_seed(3)
    col = torch.rand(500, 3, generator=g)
    vidx = torch.randint(0, 500, (1000, 3), dtype=torch.int32, generator=g)
    bw = torch.rand(1000, 3, generator=g)
    return vidx, bw, col


@pytest.mark.parametrize("q", [0, 1, 255, 256, 257, 1000])
def test_map_rows_equals_one_call_at_any_length(data, q):
    vidx, bw, col = data
    f = fused(_resolve)
    got = map_rows(f, (vidx[:q], bw[:q]), (col,), chunk=256)
    want = _resolve(vidx[:q], bw[:q], col)
    assert got.shape == want.shape == (q, 3)
    torch.testing.assert_close(got, want, rtol=1e-6, atol=1e-6)


def test_call_rows_one_variant_for_every_count_and_eager_when_empty(data):
    """`call_rows`: one call over all rows equals the eager function at 0, 1, 2 and many rows (one
    row padded to two and trimmed; none run eagerly), tuple results trimmed too, and after the
    first compiled call no count compiles another variant (the count is symbolic)."""
    from torch._dynamo.utils import counters

    vidx, bw, col = data
    f = fused(_resolve)
    for q in (1000, 0, 1, 2, 777):
        got = call_rows(f, (vidx[:q], bw[:q]), (col,))
        want = _resolve(vidx[:q], bw[:q], col)
        assert got.shape == want.shape == (q, 3)
        torch.testing.assert_close(got, want, rtol=1e-6, atol=1e-6)
        if q == 1000:
            frames = counters["stats"]["unique_graphs"]
    assert counters["stats"]["unique_graphs"] == frames
    a, b = call_rows(fused(_pair), (bw[:1],), (2.0,))
    assert a.shape == (1, 3) and b.shape == (1, 1)
    torch.testing.assert_close(a, bw[:1] * 2.0)
    with pytest.raises(ValueError, match="differ in length"):
        call_rows(_pair, (bw, bw[:10]), (2.0,))


def test_map_rows_tuple_outputs_and_length_checks(data):
    _, bw, _ = data
    a, b = map_rows(fused(_pair), (bw,), (2.0,), chunk=300)
    torch.testing.assert_close(a, bw * 2.0)
    torch.testing.assert_close(b, bw.sum(1, keepdim=True))
    with pytest.raises(ValueError, match="differ in length"):
        map_rows(_pair, (bw, bw[:10]), (2.0,))
    with pytest.raises(ValueError, match="at least one"):
        map_rows(_pair, (), (2.0,))


def test_thread_count_does_not_change_the_compiled_result(data):
    vidx, bw, col = data
    f = fused(_resolve)
    with torch_threads(1):
        one = map_rows(f, (vidx, bw), (col,), chunk=512)
    with torch_threads(2):
        two = map_rows(f, (vidx, bw), (col,), chunk=512)
    assert torch.equal(one, two)


def test_off_switch_runs_eagerly_and_bad_input_raises_the_eager_error(data, monkeypatch):
    vidx, bw, col = data
    calls = []

    def traced(v, b, c):
        calls.append(1)
        return _resolve(v, b, c)

    monkeypatch.setenv("PRTBENCH_COMPILE", "0")
    f = fused(traced)
    f(vidx, bw, col)
    assert calls == [1]   # eager: the Python body ran (a compiled call would not append)
    monkeypatch.delenv("PRTBENCH_COMPILE")
    g = fused(_resolve)
    with pytest.raises((RuntimeError, IndexError)):
        g(vidx, bw[:10], col)   # shapes disagree: the eager function's error, not a warning


def _scale_table(table, x):
    return table * x


def test_many_table_sizes_stay_compiled_and_past_the_limit_warn(monkeypatch):
    """A study's ladder gives a fused function more table sizes than Dynamo's default of 8: each
    still compiles (no fallback warning); past `RECOMPILE_LIMIT` the fallback is announced, never
    silent."""
    import warnings

    from methods.core import fused as fmod

    f = fused(_scale_table)
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        for n in range(1, 13):
            torch.testing.assert_close(f(torch.ones(n), 2.0), torch.full((n,), 2.0))
    monkeypatch.setattr(fmod, "RECOMPILE_LIMIT", 2)
    import torch._dynamo.config as dc
    monkeypatch.setattr(dc, "recompile_limit", 2)
    g = fused(_pair)
    with pytest.warns(RuntimeWarning, match="could not compile"):
        for n in range(1, 6):
            a, _ = g(torch.ones(n, 2), 3.0)
            torch.testing.assert_close(a, torch.full((n, 2), 3.0))


def _graphs() -> int:
    from torch._dynamo.utils import counters
    return int(counters["stats"]["unique_graphs"])


def _bumped(vidx, bw, col):  # a distinct function per test: its own compiled variants
    return (col[vidx.long()] * bw[..., None]).sum(1) + 1.0


def _scaled(vidx, bw, col):
    return (col[vidx.long()] * bw[..., None]).sum(1) * 2.0


def test_warming_compiles_the_neighbour_blocks_so_a_later_count_does_not_retrace(data):
    """A block size that follows a per-frame count (`pow2_block`) compiled a new variant inside a
    timed frame the first time a count landed in a new size class; in `warming` (the harness's
    warm-up frame) `map_rows(warm=...)` compiles the neighbouring sizes up front."""
    from methods.core.fused import neighbour_blocks, pow2_block, warming

    vidx, bw, col = data
    lo, hi = 64, 4096

    def frame(f, q):
        B = pow2_block(q, lo, hi)
        return map_rows(f, (vidx[:q], bw[:q]), (col,), chunk=B, warm=neighbour_blocks(B, lo, hi))

    assert pow2_block(300, lo, hi) == 512 and neighbour_blocks(512, lo, hi) == (128, 256, 512, 1024, 2048)
    for fn, warm in ((_bumped, True), (_scaled, False)):
        f = fused(fn)
        with warming(warm):
            frame(f, 300)                         # the warm-up frame: block 512
        g0 = _graphs()
        for q in (1000, 130, 300):                # later frames: blocks 1024, 256, 512
            torch.testing.assert_close(frame(f, q), fn(vidx[:q], bw[:q], col), rtol=1e-6, atol=1e-6)
        assert (_graphs() - g0 == 0) if warm else (_graphs() - g0 >= 2), (fn.__name__, _graphs() - g0)


def test_warm_blocks_does_nothing_outside_warming_and_warms_once_per_signature(data):
    from methods.core.fused import warm_blocks, warming

    vidx, bw, col = data
    f = fused(_resolve)
    assert warm_blocks(f, (vidx, bw), (col,), (64, 128)) == 0
    with warming():
        assert warm_blocks(f, (vidx, bw), (col,), (64, 128)) == 2
        assert warm_blocks(f, (vidx[:5], bw[:5]), (col,), (64, 128)) == 0      # same signature
        assert warm_blocks(f, (vidx, bw), (col.double(),), (64, 128)) == 2      # a new table dtype
        assert warm_blocks(f, (vidx[:0], bw[:0]), (col,), (256,)) == 0         # nothing to repeat


def test_warm_blocks_keys_the_same_code_in_another_file_apart():
    """A same-process A/B loads the baseline checkout's copy of a module beside the new one: equal
    code objects from two files (they compare equal: the file name is not part of code equality)
    are two functions to warm, or the new copy compiles in its first timed frame."""
    from methods.core.fused import warm_blocks, warming

    src = "def block(x, s):\n    return x * s\n"
    fa, fb = ({}, {})
    exec(compile(src, "/checkout_a/kernels.py", "exec"), fa)
    exec(compile(src, "/checkout_b/kernels.py", "exec"), fb)
    assert fa["block"].__code__ == fb["block"].__code__          # what made them one key before
    x = torch.rand(10, 3)
    with warming():
        assert warm_blocks(fa["block"], (x,), (2.0,), (16,)) == 1
        assert warm_blocks(fb["block"], (x,), (2.0,), (16,)) == 1
        assert warm_blocks(fb["block"], (x,), (2.0,), (16,)) == 0


def test_strided_rows_compile_one_variant_for_full_and_padded_blocks():
    """Rows that are a column of a wider array (stride > 1) are made contiguous first: full blocks
    (views) and the padded last block (a copy) then share one compiled variant (in-out's window
    columns compiled two)."""
    g = torch.Generator().manual_seed(5)
    col = torch.rand(50, 3, generator=g)
    win = torch.randint(0, 50, (700, 3), generator=g)
    f = fused(lambda a, b, t: t[a] + t[b])
    g0 = _graphs()
    got = map_rows(f, (win[:, 0], win[:, 1]), (col,), chunk=256)
    assert _graphs() - g0 == 1
    torch.testing.assert_close(got, col[win[:, 0]] + col[win[:, 1]])


def test_map_rows_out_equals_the_concatenation():
    """``map_rows(out=...)`` writes each block's results into the given rows (a tensor, or a tuple of
    them) and returns them: the same values as the concatenated result, padded last block trimmed."""
    from methods.core.fused import map_rows

    x, y = torch.arange(10.0), torch.arange(10.0) * 3

    def f(a, b):
        return a + b, a * b

    want = map_rows(f, [x, y], chunk=4)
    out = (torch.full((10,), -1.0), torch.full((10,), -1.0))
    got = map_rows(f, [x, y], chunk=4, out=out)
    assert got is out and all(torch.equal(g, w) for g, w in zip(got, want))
    one = torch.full((10,), -1.0)
    assert map_rows(lambda a: a * 2, [x], chunk=3, out=one) is one and torch.equal(one, x * 2)
