"""Shared fixtures of the zh_shadow tests: a thin-part test object (issue 19 item 2)."""
from __future__ import annotations

import math

import numpy as np
import pytest


def thin_part_scene(size: str = "test"):
    """A mug with a thin ring handle and a thin spout on a ground plane under the `window` probe.

    The case of issue 19: an object with thin parts (handle, spout) on a ground plane under a probe
    whose energy sits in one small, very bright source (here the window of a dim room; under
    `sky_sun` the same object has far fewer negative pixels). Handle: a torus of tube radius 0.05
    (ring radius 0.35) standing beside the body; spout: a capsule of radius 0.04; the key light is
    aimed from azimuth 70° so the thin parts cast shadows in view. 1089 vertices.
    """
    from scenes import procedural as P
    from scenes.camera import Camera
    from scenes.library import SIZES, _env, graded_plane
    from scenes.materials import Lambert, Phong
    from scenes.scene import Scene, Shape

    if size != "test":
        raise ValueError(f"the thin-part scene exists at size 'test' only, got {size!r}")
    film = SIZES[size]["film"]
    prof = [(0.0, 0.0), (0.38, 0.0), (0.4, 0.03)] + [(0.4, y) for y in np.linspace(0.1, 0.85, 6)] + \
           [(0.38, 0.9), (0.0, 0.9)]
    body = P.lathe(P._clean(prof), 20)
    c, s = math.cos(math.pi / 2), math.sin(math.pi / 2)
    Rx = np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])      # ring in the XY plane
    ring = P.torus_knot(1, 0, n_u=40, n_v=8, R=0.6, r_tube=0.05 / 0.35, scale=0.35)
    handle = P._affine(ring, R=Rx, translate=(0.62, 0.45, 0.0))
    spout = P.capsule((-0.35, 0.35, 0.0), (-0.85, 0.8, 0.0), 0.04, n_seg=8, n_len=8, n_cap=3)
    shapes = [Shape("body", "object", body), Shape("handle", "object", handle), Shape("spout", "object", spout),
              Shape("ground", "ground", graded_plane(30.0, 20))]
    cam = Camera((0.4, 2.0, 3.0), (0.0, 0.45, 0.0), (0.0, 1.0, 0.0), 42.0, film, film)
    mats = {"object": Phong(kd=(0.45, 0.4, 0.35), ks=(0.3, 0.3, 0.3), s=30.0), "ground": Lambert(kd=(0.6, 0.6, 0.6))}
    return Scene("thin_parts", shapes, ["object", "ground"], cam, _env("window", size, 70.0), mats, size=size)


@pytest.fixture(scope="session")
def thin_scene():
    return thin_part_scene("test")


def phong_chess(size: str = "test"):
    """The library `chess` with Phong stand-ins for the BRDFs zh_shadow does not support (it renders
    Lambert and Phong only): white Blinn–Phong s = 60 → Phong s = 15 (the half-vector exponent is
    ~4× the reflection-vector one), black Cook–Torrance m = 0.25 → Phong s = 2/m² − 2 = 30; same kd, ks.
    References are rendered with the same stand-ins, so the comparison is exact in the BRDFs."""
    from scenes.library import get_scene
    from scenes.materials import Phong

    sc = get_scene("chess", size)
    w, b, board = (sc.materials[r] for r in ("white", "black", "board"))
    mats = {"white": Phong(kd=w.kd, ks=w.ks, s=15.0), "black": Phong(kd=b.kd, ks=b.ks, s=30.0), "board": board}
    return sc.replace(materials=mats)


def generic_creature(size: str = "test"):
    """The library `creature` with an anonymous skeleton: its P sequences are then the generic
    per-joint sinusoids of `scenes.sequences` (each joint at its own seeded phase), as for any
    skinned character without the creature's hand-made walk — so poses of one seed's clip lie off
    another seed's (the case of a rigged character whose frames leave the training clip)."""
    import dataclasses

    from scenes.library import get_scene

    sc = get_scene("creature", size)
    return sc.replace(name="creature_generic", skeleton=dataclasses.replace(sc.skeleton, names=None))


@pytest.fixture(scope="session")
def zh_scene():
    """Callable name → test-size scene: the library scenes zh_shadow renders (chess with Phong
    stand-ins, `phong_chess`), "thin_parts" (`thin_part_scene`) and "creature_generic"
    (`generic_creature`)."""
    from scenes.library import get_scene

    special = {"thin_parts": thin_part_scene, "chess": phong_chess, "creature_generic": generic_creature}
    built = {}

    def get(name: str):
        if name not in built:
            built[name] = special[name]() if name in special else get_scene(name, "test")
        return built[name]

    return get


# the creature (test size) precomputed by ZH with the tests' small fit: one per test module that asks
_SMALL = dict(train_poses=4, n_dirs=64, fit_iters=0)


@pytest.fixture(scope="module")
def creature():
    """ZH's paper configuration (order 4, sample shading) precomputed on the test-size creature."""
    from methods.zh_shadow import ZHShadow
    from scenes.library import get_scene

    m = ZHShadow(**_SMALL)
    m.precompute(get_scene("creature", "test"))
    return m


@pytest.fixture(scope="module")
def order8():
    """ZH's order-8 vertex configuration with the cosine specular, precomputed on the test-size creature."""
    from methods.zh_shadow import ZHShadow
    from scenes.library import get_scene

    m = ZHShadow(**_SMALL, order=8, specular="cosine", shading="vertex")
    m.precompute(get_scene("creature", "test"))
    return m


def assert_frames_equal(scene, new, orc, kind: str, seed: int, *, n: int = 4, before_oracle=None,
                        fused: bool = False) -> None:
    """Render ``n`` frames of ``kind`` (``seed``) with ``new`` and its oracle ``orc``, each at 1 and 2 threads: the
    same path (and ``last_fused`` with ``fused``), the same image bits, the same counts (``plane_vertices`` by value).
    ``before_oracle(orc)``: called before each oracle frame (e.g. forgetting its kept objects)."""
    import torch

    from methods.core.threads import torch_threads
    from references.gbuffer import make_gbuffer
    from scenes.sequences import make_sequence

    for fr in make_sequence(scene, kind, n, seed=seed):
        gb = make_gbuffer(scene, fr, 2)
        for threads in (1, 2):
            with torch_threads(threads):
                a = new.render(fr, gb)
                if before_oracle is not None:
                    before_oracle(orc)
                b = orc.render(fr, gb)
            assert new.last_path == orc.last_path
            assert not fused or new.last_fused == orc.last_fused
            assert torch.equal(a.contiguous().view(torch.int32), b.contiguous().view(torch.int32)), \
                (kind, fr.index, threads, float((a - b).abs().max()))
        ca, cb = dict(new._last_counts), dict(orc._last_counts)
        pa, pb = ca.pop("plane_vertices", None), cb.pop("plane_vertices", None)
        assert ca == cb and (pa is None) == (pb is None) and (pa is None or pa() == pb())
