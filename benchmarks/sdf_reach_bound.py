"""How close can *any* cage get to an input vertex? A lower bound, cage-independent (issue 17).

A cage that contains the input and keeps a clearance ``delta`` from it (every cage point outside the
input and at least ``delta`` from its surface) lies in

    R_delta = {x outside the input : udf(x) >= delta}        (udf = unsigned distance to the surface),

and, being connected and reaching beyond the input's extremes, in the *unbounded* component of
``R_delta``. So the input-to-cage distance of an input vertex ``p`` is at least ``dist(p, R_delta^inf)``,
whatever the cage's shape, face count or method. This script bounds that from below on a grid of spacing
``h`` over a box around the given vertices (``m = h sqrt(3) / 2``): ``udf`` is 1-Lipschitz, so a path in
``R_delta`` only crosses cells whose 8 corners have ``udf >= delta - 2m`` (6-connected nodes), those nodes
split into one-sided components (``delta - 2m > h / 2``: no grid edge between two of them crosses the
surface; one winding number per component), and within the box the unbounded component can only show as
outside components that touch the box's faces (cavities and pockets closed off inside the box are
dropped). Hence

    dist(p, R_delta^inf) >= min(dist(p, nodes of those components), dist(p, outside the box)) - m.

A small bound does not prove a cage can get there (a component touching the box may still be a pocket
closed off beyond it; a larger ``--reach`` checks), but a bound above the goal (1.5% of the diagonal)
proves that no cage with that clearance meets it. The vertices come from a
``benchmarks/sdf_far_points.py`` JSON (the sdf cage's farthest input vertices, in the backend's
unit-diagonal frame). ``--envelopes`` also records the sdf envelope's distance at those vertices for a
few grids and the optional concave pass.

Usage::

    python benchmarks/sdf_reach_bound.py ZOO_DIR/homer.obj \\
        benchmarks/results/sdf/far_points_homer.json --out benchmarks/results/sdf/reach_bound_homer.json
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
from exp_common import read_mesh


def reach_bound(
    Vn: np.ndarray,
    F: np.ndarray,
    P: np.ndarray,
    deltas: list[float],
    h: float,
    reach: float,
    chunk: int = 2_000_000,
) -> dict:
    """Lower bounds on ``dist(p, R_delta)`` for every row ``p`` of ``P`` and every ``delta``.

    Parameters
    ----------
    Vn, F : (n, 3) float array, (m, 3) int array
        Closed input surface (any frame; ``P``, ``deltas``, ``h``, ``reach`` in the same units).
    P : (k, 3) float array
        Query points (input vertices).
    deltas : list of float
        Clearances; each must exceed ``h * sqrt(3)``.
    h : float
        Grid spacing.
    reach : float
        The grid box is the bounding box of ``P`` grown by ``reach``; bounds are capped at ``reach - m``.

    Returns
    -------
    dict
        ``bounds[delta]``: list of per-point lower bounds; grid size and seconds.
    """
    import igl
    from scipy import ndimage
    from scipy.spatial import cKDTree

    m = h * np.sqrt(3) / 2
    if min(deltas) <= 2 * m + h / 2:
        raise ValueError(f"every delta must exceed 2 m + h / 2 = {2 * m + h / 2:.3g} (h = {h:.3g}); use a smaller --h")
    lo, hi = P.min(0) - reach, P.max(0) + reach
    axes = [np.arange(a, b + h, h) for a, b in zip(lo, hi)]
    shape = tuple(len(a) for a in axes)
    n = int(np.prod(shape))
    t0 = time.perf_counter()
    tree = igl.AABB()
    tree.init(Vn, F)
    udf = np.empty(n)
    for s in range(0, n, chunk):
        idx = np.arange(s, min(n, s + chunk))
        i, j, k = np.unravel_index(idx, shape)
        Q = np.column_stack([axes[0][i], axes[1][j], axes[2][k]])
        udf[idx] = np.sqrt(tree.squared_distance(Vn, F, Q)[0])
    udf = udf.reshape(shape)
    seconds = time.perf_counter() - t0
    # distance from each p to the outside of the box: a point of R_delta beyond the box is at least this far
    to_box = np.minimum((P - lo).min(1), (hi - P).min(1))
    bounds, outside_nodes = {}, {}
    flat = np.arange(n).reshape(shape)  # flat node index, for one representative node per component
    for delta in deltas:
        # Nodes with udf >= delta - 2m: every cell a path in R_delta passes through has all 8 corners
        # there, so R_delta's connectivity survives as 6-connectivity of those nodes; and since
        # delta - 2m > h/2, the edge between two such neighbours cannot cross the surface, so each
        # component lies on one side (one winding number per component, |w| < 0.5: either orientation).
        labels, n_comp = ndimage.label(udf >= delta - 2 * m)
        first = ndimage.minimum_position(flat, labels, np.arange(1, n_comp + 1))
        reps = np.array([[axes[a][c[a]] for a in range(3)] for c in first]).reshape(-1, 3)
        keep = np.concatenate([[False], np.abs(igl.fast_winding_number(Vn, F, reps)) < 0.5])
        # The cage is connected, keeps the clearance and reaches beyond the input's extremes, so it lies
        # in the unbounded component of R_delta; within the box that component only has nodes in
        # components that touch the box's faces (a cavity, or a pocket closed off inside the box, does not).
        faces = np.zeros(n_comp + 1, bool)
        for a in range(3):
            for end in (0, -1):
                faces[np.unique(np.take(labels, end, axis=a))] = True
        keep &= faces
        i, j, k = np.nonzero(keep[labels])
        G = np.column_stack([axes[0][i], axes[1][j], axes[2][k]])
        d = cKDTree(G).query(P)[0] if len(G) else np.full(len(P), np.inf)
        bounds[str(delta)] = (np.minimum(d, to_box) - m).tolist()
        outside_nodes[str(delta)] = len(G)
    return {"grid_shape": list(shape), "h": h, "margin": m, "reach": reach, "grid_seconds": seconds,
            "outside_nodes": outside_nodes, "bounds": bounds}


def envelopes(Vn: np.ndarray, F: np.ndarray, ids: np.ndarray, grids: list[tuple[float, float]], c: float = 0.01) -> list:
    """Input-to-envelope distances of ``build_envelope`` for ``(h / c, concave)`` pairs: where the offset bridges."""
    from cagegen.envelope import _genus, build_envelope
    from cagegen.sdf.tighten import input_to_cage

    out = []
    for hc, concave in grids:
        t = time.perf_counter()
        env = build_envelope(Vn, F, c=c, h=hc * c, concave=concave)
        d = input_to_cage(Vn, F, env.V, env.F)[0]
        rec = env.info.get("concave", {})
        out.append({"h_over_c": hc, "concave": concave, "faces": len(env.F), "genus": _genus(env.V, env.F),
                    "input_to_envelope_max": float(d.max()), "n_beyond_1.5pct": int((d > 0.015).sum()),
                    "at_vertices": d[ids].tolist(), "concave_used": rec.get("used"),
                    "concave_genus": [rec.get("genus_before"), rec.get("genus_after")],
                    "seconds": time.perf_counter() - t})
        print(f"envelope h = {hc:.3g} c, concave {concave}: {out[-1]['faces']} faces, genus {out[-1]['genus']}, "
              f"input-to-envelope max {d.max():.4f}, at the vertices <= {d[ids].max():.4f}, concave pass used: "
              f"{rec.get('used')} (genus {rec.get('genus_before')} -> {rec.get('genus_after')})", flush=True)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("mesh")
    ap.add_argument("far_points", help="JSON of benchmarks/sdf_far_points.py")
    ap.add_argument("--out", required=True)
    ap.add_argument("--deltas", default="3e-4,5e-4,1e-3", help="clearances over the diagonal")
    ap.add_argument("--h", type=float, default=1.2e-4, help="grid spacing over the diagonal")
    ap.add_argument("--reach", type=float, default=0.016, help="box margin around the vertices")
    ap.add_argument("--envelopes", default="", help="also build sdf envelopes (c = 0.01) for these "
                    "'h_over_c:concave' pairs, e.g. '1:0,1:1.5,0.5:1.5', and record where they bridge")
    a = ap.parse_args()
    V, F = read_mesh(Path(a.mesh))
    lo, hi = V.min(0), V.max(0)
    center, unit = 0.5 * (lo + hi), float(np.linalg.norm(hi - lo))  # as sdf_far_points.py
    Vn = (V - center) / unit
    rec = json.loads(Path(a.far_points).read_text())["results"][Path(a.mesh).name]
    ids = np.array([r["vertex"] for r in rec["farthest"]])
    cage_d = [r["distance"] for r in rec["farthest"]]
    deltas = [float(x) for x in a.deltas.split(",")]
    res = reach_bound(Vn, F.astype(np.int64), Vn[ids], deltas, a.h, a.reach)
    res.update(command=" ".join(sys.argv), mesh=Path(a.mesh).name, vertices=ids.tolist(),
               sdf_cage_distance=cage_d, far_points_json=a.far_points)
    if a.envelopes:
        grids = [tuple(float(x) for x in g.split(":")) for g in a.envelopes.split(",")]
        res["envelopes"] = envelopes(Vn, F.astype(np.int64), ids, grids)
    Path(a.out).write_text(json.dumps(res, indent=1))
    print(f"grid {res['grid_shape']} in {res['grid_seconds']:.1f} s; margin {res['margin']:.2e}")
    for delta, b in res["bounds"].items():
        print(f"delta {delta}: max lower bound {max(b):.4f}, per vertex {np.round(b, 4).tolist()}")


if __name__ == "__main__":
    main()
