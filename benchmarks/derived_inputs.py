"""The derived inputs of docs/scale.md, made from the dev zoo: subdivided and noisy copies.

    python benchmarks/derived_inputs.py ZOO_DIR OUT_DIR

writes ``gargo_21k.obj`` and ``gargo_342k.obj`` (``gargo.off`` loop-subdivided once and three times),
``bunny_111k.obj`` (``bunny.off`` loop-subdivided twice), ``homer_192k.obj`` (``homer.obj`` loop-subdivided
twice: thin limbs, for the nested backend's time model), ``gargo_86k_noisy.obj`` (``gargo.off``
loop-subdivided twice, every vertex moved along its area-weighted normal by a uniform random amount in
±0.25 of the mean edge, ``numpy.random.default_rng(0)``: a scan-like noisy surface) and
``fandisk_207k_flat.obj`` (``fandisk.obj`` split twice by ``igl.upsample``, every face in four in its own
plane: a finely tessellated CAD part whose many exactly coplanar faces send the audit's self-intersection
test to its exact arithmetic). Face counts: 21,376, 342,016, 111,456, 192,000, 85,504 and 207,136. Nothing
of the zoo is modified.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import igl
import numpy as np

from nestmg.io import load_mesh, save_mesh

#: output name -> (zoo file, subdivisions, noise amplitude in mean edges, scheme: "loop" or "flat")
DERIVED = {
    "gargo_21k.obj": ("gargo.off", 1, 0.0, "loop"),
    "gargo_342k.obj": ("gargo.off", 3, 0.0, "loop"),
    "bunny_111k.obj": ("bunny.off", 2, 0.0, "loop"),
    "homer_192k.obj": ("homer.obj", 2, 0.0, "loop"),
    "gargo_86k_noisy.obj": ("gargo.off", 2, 0.25, "loop"),
    "fandisk_207k_flat.obj": ("fandisk.obj", 2, 0.0, "flat"),
}


def derive(V: np.ndarray, F: np.ndarray, subdivisions: int, noise: float, seed: int = 0, scheme: str = "loop"):
    """``(V, F)`` subdivided ``subdivisions`` times (``"loop"``: Loop's smooth scheme; ``"flat"``: every face in
    four in its own plane, ``igl.upsample``), then moved along its normals by ±``noise`` mean edges."""
    V, F = np.asarray(V, dtype=np.float64), np.asarray(F, dtype=np.int64)
    if subdivisions and scheme == "flat":
        V, F = igl.upsample(V, F, subdivisions)
    elif subdivisions:
        V, F = igl.loop(V, F, subdivisions)
    if noise:
        E = V[F[:, [1, 2, 0]]] - V[F]
        mean_edge = float(np.linalg.norm(E, axis=2).mean())
        N = igl.per_vertex_normals(V, F, igl.PER_VERTEX_NORMALS_WEIGHTING_TYPE_AREA)
        t = np.random.default_rng(seed).uniform(-noise, noise, len(V)) * mean_edge
        V = V + t[:, None] * N
    return V, F


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("zoo", type=Path, help="the dev zoo folder (gargo.off, bunny.off, homer.obj, fandisk.obj)")
    ap.add_argument("out", type=Path, help="folder for the derived meshes (created)")
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    for name, (src, subdivisions, noise, scheme) in DERIVED.items():
        V, F = derive(*load_mesh(str(args.zoo / src)), subdivisions, noise, scheme=scheme)
        save_mesh(args.out / name, V, F)
        print(f"{name}: {len(F):,} faces from {src}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
