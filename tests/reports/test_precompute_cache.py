"""The precompute cache (reports.precompute_cache): storage that cannot run code, damaged entries
detected and recomputed, the size cap with least-recently-used pruning, the ``cache`` CLI.

Round trips of the real methods are in test_precompute_cache_methods.py."""
from __future__ import annotations

import collections
import io
import json
import math
import os
import pickle
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import torch

from methods.base import Capabilities, Method
from methods.zh_shadow.precompute import ZHModel
from reports import precompute_cache as PC
from scenes.materials import Lambert, Phong

N = 4096  # floats in the test method's state (a 16 KiB tensor: entries of a known, equal size)


class _Scene:
    """What the cache needs of a scene: a name and a content hash."""

    def __init__(self, name: str = "s") -> None:
        self.name = name

    def content_hash(self) -> str:
        return "hash-" + self.name


CALLS: list[float] = []


class Counting(Method):
    """Opts in to the cache; its state mixes tensors, a sparse matrix, classes of ours and the scene."""

    name = "counting_test"
    capabilities = Capabilities()
    cache_precompute = True

    def __init__(self, *, k: float = 1.0) -> None:
        super().__init__(k=k)
        self.scene = None
        self.table: torch.Tensor | None = None

    def precompute(self, scene) -> None:
        CALLS.append(self.config["k"])
        self.scene = scene
        self.table = torch.arange(N, dtype=torch.float32) * self.config["k"]
        self.model = ZHModel(self.table[:12].view(1, 1, 12).clone(), 4, 2)
        self.sparse = torch.eye(5).to_sparse_csr()

    def render(self, frame, gbuffer):
        raise NotImplementedError

    def memory(self):
        return {}


@pytest.fixture(autouse=True)
def cache(tmp_path, monkeypatch):
    monkeypatch.setenv("PRTBENCH_CACHE", str(tmp_path / "cache"))
    monkeypatch.delenv("PRTBENCH_NO_PRECOMPUTE_CACHE", raising=False)
    monkeypatch.delenv(PC.ENV_MAX_GB, raising=False)
    CALLS.clear()
    return tmp_path / "cache" / "precompute"


def _fresh(scene, k=1.0):
    m = Counting(k=k)
    info = PC.precompute(m, scene, json.dumps({"k": k}))
    return m, info


def _check(m, scene, k=1.0):
    assert m.scene is scene                              # a reference to the live scene, not a copy
    assert torch.equal(m.table, torch.arange(N, dtype=torch.float32) * k)
    assert isinstance(m.model, ZHModel) and m.model.order == 4 and torch.equal(m.model.X.flatten(), m.table[:12])
    assert m.sparse.layout == torch.sparse_csr and torch.equal(m.sparse.to_dense(), torch.eye(5))


# -- the codec --------------------------------------------------------------------------------


def test_codec_round_trips_every_kind_of_state_bit_for_bit():
    scene = _Scene()
    base = torch.randn(6, 7, dtype=torch.float64)
    shared = [1, 2]
    cyc: list = []
    cyc.append(cyc)
    g = torch.randn(3, requires_grad=True)
    state = {
        "dense": base, "view": base[1:, ::2].t(), "int": torch.arange(5, dtype=torch.int16), "bool": base > 0,
        "half": base.to(torch.bfloat16), "grad": g, "coo": torch.randn(4, 4).relu().to_sparse(),
        "csr": torch.randn(5, 3).relu().to_sparse_csr(),
        "np": np.arange(12, dtype=np.float32).reshape(3, 4)[:, ::2], "np_bool": np.array([True, False]),
        "np_ro": np.ones(3, dtype=np.int64), "np_f64": np.float64(0.1), "np_i": np.int32(-7),
        "floats": [0.1, -0.0, math.inf, -math.inf, math.nan, 1e308, 5e-324], "big": 2**80, "c": 1 + 2j,
        "s": "ünïcode", "b": b"\x00\xff", "none": None, "t": (1, (2.5, "x")), "set": {3, 1}, "fs": frozenset({"a"}),
        "size": torch.Size([2, 3]), "dtype": torch.float16, "device": torch.device("cpu"),
        "path": Path("/a/b"), "keys": {0.5: "half", (1, 2): "tuple", 3: "int", None: "none"},
        "alias_a": shared, "alias_b": shared, "same_t1": base, "cycle": cyc,
        "ours": [Phong(kd=(0.1, 0.2, 0.3), ks=(0.5, 0.5, 0.5), s=12.0), Lambert(kd=(0.4, 0.4, 0.4))],
        "frozen": Capabilities(dynamic_brdf=True, brdfs=frozenset({"phong"})), "scene": scene,
    }
    state["np_ro"].flags.writeable = False
    tree, tensors = PC.encode_state(state, scene)
    buf = io.BytesIO()
    torch.save({"tree": tree, "tensors": tensors}, buf)
    buf.seek(0)
    blob = torch.load(buf, weights_only=True)
    out = PC.decode_state(blob["tree"], blob["tensors"], scene)

    assert out.keys() == state.keys()
    for k in ("dense", "view", "int", "bool", "half", "coo", "csr"):
        a, b = state[k], out[k]
        assert a.layout == b.layout and a.dtype == b.dtype and a.shape == b.shape, k
        assert torch.equal(a.to_dense(), b.to_dense()), k
    assert out["view"].stride() == state["view"].stride()
    assert out["view"].untyped_storage().data_ptr() == out["dense"].untyped_storage().data_ptr()  # one storage
    assert out["grad"].requires_grad and torch.equal(out["grad"].detach(), g.detach())
    for k in ("np", "np_bool", "np_ro"):
        assert type(out[k]) is np.ndarray and out[k].dtype == state[k].dtype and np.array_equal(out[k], state[k])
    assert not out["np_ro"].flags.writeable
    assert type(out["np_f64"]) is np.float64 and out["np_f64"] == np.float64(0.1)
    assert type(out["np_i"]) is np.int32 and out["np_i"] == -7
    f = out["floats"]
    assert f[0] == 0.1 and math.copysign(1, f[1]) == -1 and f[2:4] == [math.inf, -math.inf] and math.isnan(f[4])
    assert f[5:] == [1e308, 5e-324]
    for k in ("big", "c", "s", "b", "none", "t", "set", "fs", "size", "dtype", "device", "path", "keys"):
        assert out[k] == state[k] and type(out[k]) is type(state[k]), k
    assert out["alias_a"] is out["alias_b"] and out["same_t1"] is out["dense"]   # aliasing kept
    assert out["cycle"][0] is out["cycle"]                                         # and cycles
    assert out["ours"] == state["ours"] and type(out["ours"][0]) is Phong
    assert out["frozen"] == state["frozen"] and out["scene"] is scene


def _lock_state():
    return {"lock": threading.Lock()}


@dataclass
class _Local:  # a class of the test module: not in methods/ or scenes/
    x: int = 1


@pytest.mark.parametrize("bad, where", [
    ({"f": lambda x: x}, "state['f']"),
    (_lock_state(), "state['lock']"),
    ({"nested": {"obj": [_Local()]}}, "state['nested']['obj'][0]"),
    ({"od": collections.OrderedDict(a=1)}, "state['od']"),
    ({"cls": Phong}, "state['cls']"),
    ({"objs": np.array([object()])}, "state['objs']"),
    ({"gen": torch.Generator()}, "state['gen']"),
    ({"mod": os}, "state['mod']"),
])
def test_codec_refuses_anything_it_cannot_rebuild_without_running_code(bad, where):
    with pytest.raises(PC.NotCacheable) as e:
        PC.encode_state(bad)
    assert str(e.value).startswith(where + ":"), str(e.value)


@pytest.mark.parametrize("cls", ["os:system", "builtins:eval", "subprocess:Popen", "methods.base:Tensor",
                                 "methods.registry:get_method", "methods.base:MappingProxyType", "methods.base:Method.render",
                                 "scenes.materials:Phong.__init__", "methods:../os", "methods.nonexistent:X",
                                 "testing.fakes:FakeMethod", "methods.base:<locals>.X", 42])
def test_decoder_resolves_only_classes_defined_in_our_packages(cls):
    """A tree naming anything but a class defined in methods/ or scenes/ is refused before any
    call: no function, no imported alias (methods.base imports torch's Tensor), no other package."""
    tree = json.dumps({"$": "dict", "id": 0, "items": [["x", {"$": "obj", "cls": cls, "id": 1, "state": []}]]})
    with pytest.raises(PC.CorruptEntry):
        PC.decode_state(tree, [])


def test_decoding_a_sparse_csr_entry_prints_no_beta_warning(tmp_path):
    """torch warns "Sparse CSR tensor support is in beta state" once per process at the first CSR it builds; a
    cached precompute (in-out's transport) must not print it into every run's log. The entry is encoded here and
    decoded in a fresh interpreter that has built no CSR yet (this process may already have spent the warning)."""
    import subprocess
    import sys
    tree, tensors = PC.encode_state({"csr": torch.eye(3).to_sparse_csr()}, None)
    torch.save({"tree": tree, "tensors": tensors}, tmp_path / "entry.pt")
    code = ("import sys, torch, warnings\n"
            "from reports import precompute_cache as PC\n"
            "blob = torch.load(sys.argv[1], weights_only=True)\n"
            "with warnings.catch_warnings(record=True) as w:\n"
            "    warnings.simplefilter('always')\n"
            "    out = PC.decode_state(blob['tree'], blob['tensors'], None)\n"
            "assert out['csr'].layout == torch.sparse_csr and torch.equal(out['csr'].to_dense(), torch.eye(3))\n"
            "print('WARNINGS', [str(x.message) for x in w])\n")
    r = subprocess.run([sys.executable, "-c", code, str(tmp_path / "entry.pt")], capture_output=True, text=True,
                       timeout=120, cwd=Path(__file__).resolve().parents[2])
    assert r.returncode == 0, r.stderr
    assert "WARNINGS []" in r.stdout and "beta" not in r.stderr, (r.stdout, r.stderr)


def test_decoder_checks_sparse_invariants():
    """Out-of-range indices in a file must not reach a sparse kernel."""
    tree = json.dumps({"$": "dict", "id": 0, "items": [["s", {"$": "sparse_csr", "id": 1, "size": [2, 2],
                                                                 "crow": 0, "col": 1, "values": 2}]]})
    bad = [torch.tensor([0, 1, 2]), torch.tensor([0, 7]), torch.ones(2)]
    with pytest.raises(PC.CorruptEntry):
        PC.decode_state(tree, bad)


# -- planted payloads, damaged entries ---------------------------------------------------------


class _Payload:
    """Unpickling calls open(sentinel, "w"): creates the file."""

    def __init__(self, sentinel: Path) -> None:
        self.sentinel = str(sentinel)

    def __reduce__(self):
        return (open, (self.sentinel, "w"))


def _payload_bytes(sentinel: Path, kind: str) -> bytes:
    if kind == "pickle":
        return pickle.dumps(_Payload(sentinel))
    buf = io.BytesIO()
    torch.save({"format": PC.FORMAT, "version": PC.VERSION, "tree": "{}", "tensors": [], "x": _Payload(sentinel)},
               buf)
    return buf.getvalue()


def _entry_files(folder: Path) -> tuple[Path, Path]:
    (side,) = folder.glob("*.json")
    (data,) = folder.glob("*.pt")
    return side, data


def _plant(side: Path, data_bytes: bytes, how: str) -> None:
    """Put ``data_bytes`` where the entry's data is read from. "over": overwrite the data file the
    sidecar names (hash now wrong); "consistent": a data file named for its hash and a sidecar
    whose sha256 and size match it (every integrity check passes)."""
    meta = json.loads(side.read_text()) if side.exists() else {
        "format": PC.FORMAT, "version": PC.VERSION, "class": Counting.__qualname__, "seconds": 1.0}
    if how == "over":
        side.with_name(meta["data"]).write_bytes(data_bytes)
        return
    import hashlib

    sha = hashlib.sha256(data_bytes).hexdigest()
    name = f"{side.stem}.{sha[:16]}.pt"
    side.with_name(name).write_bytes(data_bytes)
    side.write_text(json.dumps(meta | {"sha256": sha, "bytes": len(data_bytes), "data": name}))


@pytest.mark.parametrize("kind", ["pickle", "torch"])
@pytest.mark.parametrize("how", ["over", "consistent", "fresh"])
def test_planted_pickle_payload_runs_nothing_and_is_recomputed(cache, tmp_path, kind, how):
    """A __reduce__ payload planted as the entry's data file (raw pickle or inside a torch archive;
    with a stale sidecar, with a sidecar that matches it, or as a brand-new entry) runs nothing:
    the entry is reported, deleted and recomputed correctly."""
    scene = _Scene()
    live = tmp_path / "live"
    pickle.loads(_payload_bytes(live, "pickle"))       # the payload is live: unpickling runs it
    assert live.exists()
    sentinel = tmp_path / "pwned"
    if how == "fresh":
        side = PC.cache_path(scene, Counting(), json.dumps({"k": 1.0}))
    else:
        _fresh(scene)
        side, _ = _entry_files(cache)
    _plant(side, _payload_bytes(sentinel, kind), "over" if how == "over" else "consistent")
    with pytest.warns(UserWarning, match=r"ignoring precompute cache counting_test-\w+\.json: .*deleted, recomputing"):
        m, info = _fresh(scene)
    assert not sentinel.exists()
    assert not info["cached"] and CALLS == ([1.0] if how == "fresh" else [1.0, 1.0])
    _check(m, scene)
    m2, info2 = _fresh(scene)                          # the recomputed entry serves the next cell
    assert info2["cached"] and info2["seconds"] == info["seconds"]
    _check(m2, scene)
    assert len(list(cache.iterdir())) == 2 and not sentinel.exists()


def test_legacy_pickle_at_the_old_cache_path_is_never_loaded_and_is_pruned(cache, tmp_path):
    """Before, the entry was ``<method>-<key>.pkl`` and was pickle.load-ed."""
    scene = _Scene()
    sentinel = tmp_path / "pwned"
    side = PC.cache_path(scene, Counting(), json.dumps({"k": 1.0}))
    legacy = side.with_suffix(".pkl")
    legacy.write_bytes(_payload_bytes(sentinel, "pickle"))
    m, info = _fresh(scene)                            # computes; its write prunes the legacy file
    assert not info["cached"] and not legacy.exists() and not sentinel.exists()
    _check(m, scene)


@pytest.mark.parametrize("damage", ["truncated", "zeroed", "flipped", "empty", "missing_sidecar_fields",
                                    "sidecar_not_json", "other_class"])
def test_damaged_entry_is_detected_deleted_and_recomputed(cache, damage):
    scene = _Scene()
    _fresh(scene)
    side, data = _entry_files(cache)
    raw = data.read_bytes()
    if damage == "truncated":
        data.write_bytes(raw[: len(raw) // 2])
    elif damage == "zeroed":
        data.write_bytes(bytes(len(raw)))
    elif damage == "flipped":
        data.write_bytes(raw[:-100] + bytes([raw[-100] ^ 1]) + raw[-99:])
    elif damage == "empty":
        data.write_bytes(b"")
    elif damage == "missing_sidecar_fields":
        side.write_text(json.dumps({"format": PC.FORMAT, "version": PC.VERSION}))
    elif damage == "sidecar_not_json":
        side.write_bytes(b"\x00" * 64)
    else:
        side.write_text(json.dumps(json.loads(side.read_text()) | {"class": "Other"}))
    with pytest.warns(UserWarning, match="ignoring precompute cache") as rec:
        m, info = _fresh(scene)
    assert len(rec) == 1 and "\n" not in str(rec[0].message)  # one line
    assert not info["cached"] and CALLS == [1.0, 1.0]
    _check(m, scene)
    assert _fresh(scene)[1]["cached"]


def test_an_archive_of_the_right_format_but_unexpected_content_is_refused(cache):
    """Sparse tensors are stored as their dense parts; a file that lists one directly (or a tree
    naming a tensor it does not hold) is not ours."""
    scene = _Scene()
    _fresh(scene)
    side, _ = _entry_files(cache)
    for blob in ({"format": PC.FORMAT, "version": PC.VERSION, "tree": '{"$":"dict","id":0,"items":[]}',
                  "tensors": [torch.eye(2).to_sparse()]},
                 {"format": PC.FORMAT, "version": PC.VERSION, "tensors": [],
                  "tree": '{"$":"dict","id":0,"items":[["table",{"$":"tensor","id":1,"i":5}]]}'}):
        buf = io.BytesIO()
        torch.save(blob, buf)
        _plant(side, buf.getvalue(), "consistent")
        with pytest.warns(UserWarning, match="ignoring precompute cache"):
            m, info = _fresh(scene)
        assert not info["cached"]
        _check(m, scene)
        side, _ = _entry_files(cache)


def test_a_folder_in_place_of_an_entry_file_costs_a_warning_not_the_cell(cache):
    scene = _Scene()
    _fresh(scene)
    side, data = _entry_files(cache)
    data.unlink()
    data.mkdir()
    with pytest.warns(UserWarning, match="ignoring precompute cache"):
        m, info = _fresh(scene)
    assert not info["cached"]
    _check(m, scene)


def test_a_sidecar_cannot_make_the_cache_read_or_delete_files_elsewhere(cache, tmp_path):
    scene = _Scene()
    _fresh(scene)
    side, data = _entry_files(cache)
    victim = tmp_path / "victim.pt"
    victim.write_bytes(data.read_bytes())
    side.write_text(json.dumps(json.loads(side.read_text()) | {"data": "../../victim.pt"}))
    before = victim.read_bytes()
    with pytest.warns(UserWarning, match="data file name"):
        assert not _fresh(scene)[1]["cached"]
    assert victim.read_bytes() == before


def test_state_that_cannot_be_stored_runs_uncached_with_one_warning(cache):
    class WithLambda(Counting):
        name = "with_lambda_test"

        def precompute(self, scene):
            super().precompute(scene)
            self.f = lambda x: x

    scene = _Scene()
    with pytest.warns(UserWarning, match=r"with_lambda_test: precompute not cached.*state\['f'\]"):
        assert not PC.precompute(WithLambda(), scene, "{}")["cached"]
    assert not PC.precompute(WithLambda(), scene, "{}")["cached"]  # again computed, no second warning
    assert CALLS == [1.0, 1.0] and not any(cache.iterdir())


def test_sidecar_records_the_original_seconds_and_threads(cache):
    scene = _Scene()
    _, info = _fresh(scene)
    side, data = _entry_files(cache)
    meta = json.loads(side.read_text())
    assert meta["seconds"] == info["seconds"] and meta["threads"] == torch.get_num_threads() == info["threads"]
    assert meta["bytes"] == data.stat().st_size and meta["method"] == "counting_test"
    assert meta["created"] == meta["last_used"] and meta["config"] == json.dumps({"k": 1.0})
    time.sleep(0.01)
    _, info2 = _fresh(scene)
    meta2 = json.loads(side.read_text())
    assert info2["cached"] and meta2["last_used"] > meta["last_used"] and meta2["created"] == meta["created"]


# -- size cap, LRU pruning, CLI ---------------------------------------------------------------


def _entry_bytes(cache) -> int:
    return sum(p.stat().st_size for p in cache.iterdir())


def test_writes_prune_least_recently_used_entries_to_the_cap(cache, monkeypatch):
    scene = _Scene()
    _fresh(scene, k=1.0)
    size = _entry_bytes(cache)
    monkeypatch.setenv(PC.ENV_MAX_GB, str(2.5 * size / 1e9))    # room for two entries
    time.sleep(0.01)
    _fresh(scene, k=2.0)
    time.sleep(0.01)
    assert _fresh(scene, k=1.0)[1]["cached"]                    # k=1 used after k=2: k=2 is the LRU
    time.sleep(0.01)
    _fresh(scene, k=3.0)                                         # over the cap: k=2 goes
    assert CALLS == [1.0, 2.0, 3.0]
    assert {m["config"] for m in PC.info()["list"]} == {json.dumps({"k": 1.0}), json.dumps({"k": 3.0})}
    assert _entry_bytes(cache) <= 2.5 * size
    assert _fresh(scene, k=1.0)[1]["cached"] and _fresh(scene, k=3.0)[1]["cached"]
    assert not _fresh(scene, k=2.0)[1]["cached"]


def test_prune_removes_old_orphans_and_keeps_young_ones(cache):
    scene = _Scene()
    _fresh(scene)
    old, young = cache / "counting_test-x.0123456789abcdef.pt", cache / ".counting_test-y.abc.tmp"
    for p in (old, young):
        p.write_bytes(b"x" * 100)
    os.utime(old, (time.time() - 2 * PC.ORPHAN_GRACE_S,) * 2)
    r = PC.prune()
    assert r == {"removed": 0, "files": 1, "freed": 100, "bytes": _entry_bytes(cache)}
    assert not old.exists() and young.exists() and PC.info()["entries"] == 1


def test_bad_cap_is_one_clear_error(monkeypatch):
    for bad in ("-1", "lots", "nan", "inf"):
        monkeypatch.setenv(PC.ENV_MAX_GB, bad)
        with pytest.raises(ValueError, match=PC.ENV_MAX_GB):
            PC.max_bytes()
    monkeypatch.setenv(PC.ENV_MAX_GB, "0.5")
    assert PC.max_bytes() == 500_000_000
    monkeypatch.delenv(PC.ENV_MAX_GB)
    assert PC.max_bytes() == 20_000_000_000


def test_cli_cache_info_prune_clear(cache, capsys, monkeypatch):
    import run_bench

    scene = _Scene()
    _fresh(scene, k=1.0)
    _fresh(scene, k=2.0)
    (cache / "stale.pkl").write_bytes(b"old")
    assert run_bench.main(["cache", "info"]) == 0
    out = capsys.readouterr().out
    assert f"precompute cache {cache}: 2 entries" in out and "counting_test: 2 entries" in out
    assert "not entries (removed by prune): 1 files" in out
    size = _entry_bytes(cache) - 3
    assert run_bench.main(["cache", "prune", "--max-gb", str(0.6 * size / 1e9)]) == 0
    assert "pruned" in capsys.readouterr().out and PC.info()["entries"] == 1 and not (cache / "stale.pkl").exists()
    for bad in ("-1", "inf", "nan"):
        assert run_bench.main(["cache", "prune", "--max-gb", bad]) == 2
        assert "--max-gb must be" in capsys.readouterr().err
    monkeypatch.setenv(PC.ENV_MAX_GB, "nope")
    assert run_bench.main(["cache", "prune"]) == 2
    assert PC.ENV_MAX_GB in capsys.readouterr().err
    assert run_bench.main(["cache", "clear"]) == 0
    assert "cleared" in capsys.readouterr().out and not any(cache.iterdir())


# -- the key follows the code the method runs (not the whole tree) --------------------------------


def _copy_tree(tmp_path):
    import shutil

    from reports.store import CODE_PACKAGES
    from scenes.io import PROJECT_ROOT

    for pkg in CODE_PACKAGES:
        shutil.copytree(PROJECT_ROOT / pkg, tmp_path / pkg, ignore=shutil.ignore_patterns("__pycache__", "assets"))
    return tmp_path


def _touch(root, rel):
    p = root / rel
    p.write_text(p.read_text() + "\n# edited\n")


def test_closure_follows_module_and_function_level_imports():
    from reports.store import module_closure
    from scenes.io import PROJECT_ROOT

    rel = {str(p.relative_to(PROJECT_ROOT)) for p in module_closure("methods.inout.method")}
    assert {"methods/inout/method.py", "methods/inout/transport.py", "methods/inout/fast.py",  # module level
            "methods/inout/analysis.py",          # imported inside InOut._factorize only
            "methods/core/cubemap.py", "methods/base.py", "methods/__init__.py", "methods/inout/__init__.py"} <= rel
    assert not any(r.startswith(("reports/", "methods/ptt/", "methods/zh_shadow/")) for r in rel), rel
    with pytest.raises(ValueError, match="not a module of the project"):
        module_closure("torch.nn")


@pytest.mark.parametrize("rel, changes", [
    ("reports/html.py", False),              # the report: not run by the method
    ("methods/ptt/method.py", False),        # another method
    ("methods/inout/transport.py", True),    # its own code
    ("methods/inout/analysis.py", True),     # imported inside a function
    ("methods/core/cubemap.py", True),       # shared math it imports
    ("scenes/library.py", True),             # scene code (run through the Scene object: always included)
])
def test_precompute_key_changes_exactly_when_code_the_method_runs_changes(tmp_path, rel, changes):
    from reports.store import code_closure_fingerprint

    root = _copy_tree(tmp_path)
    before = code_closure_fingerprint("methods.inout.method", root)
    _touch(root, rel)
    assert (code_closure_fingerprint("methods.inout.method", root) != before) == changes
