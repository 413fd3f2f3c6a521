"""How many vertices a frame's samples reference, against what a per-vertex count may charge
(issue 14, session 26: the cost models of ZH and SH PRT count vertices no sample sees).

    python -m benchmarks.referenced_vertices [--scene creature] [--size bench] [--kinds V P]
                                             [--frames 5] [--seed 0]

Per frame of each sequence kind (the suite's G-buffers, 2 × 2 samples per pixel): the scene's
vertex count N, the vertices of the faces the hit samples lie on ("referenced": what in-out and the
triple product count and shade), the vertices facing the camera (n · ω_o > 0 at the vertex: what ZH's
vertex shading counts) and both."""
from __future__ import annotations

import argparse

import torch

from benchmarks.common import setup


def counts(scene, frame, gbuffer) -> dict[str, int]:
    """N, referenced, front-facing and both for one frame's geometry and G-buffer."""
    geom = scene.geometry(frame.pose) if getattr(frame, "pose", None) is not None else scene.geometry()
    F = torch.as_tensor(geom.F).long()
    ref = torch.zeros(int(geom.num_vertices), dtype=torch.bool)
    ref[F[gbuffer.face[gbuffer.hit].long()].reshape(-1)] = True
    cam = torch.tensor(frame.camera.origin, dtype=torch.float32)
    wo = torch.nn.functional.normalize(cam - torch.as_tensor(geom.V).float(), dim=-1)
    front = (torch.as_tensor(geom.N).float() * wo).sum(-1) > 0
    return {"N": int(geom.num_vertices), "referenced": int(ref.sum()), "front": int(front.sum()),
            "front_referenced": int((front & ref).sum())}


def main(argv: list[str] | None = None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="creature")
    ap.add_argument("--size", default="bench")
    ap.add_argument("--kinds", nargs="+", default=["V", "P"])
    ap.add_argument("--frames", type=int, default=5)
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args(argv)
    rows = []
    for kind in a.kinds:
        scene, frames, gbs, _ = setup(a.scene, a.size, kind=kind, n_frames=a.frames, seed=a.seed, spp_side=2)
        for i, (f, g) in enumerate(zip(frames, gbs)):
            r = {"kind": kind, "frame": i, **counts(scene, f, g)}
            rows.append(r)
            print(f"{kind:4} frame {i}: N {r['N']}, referenced {r['referenced']}, front-facing {r['front']}, "
                  f"both {r['front_referenced']}")
    return rows


if __name__ == "__main__":
    main()
