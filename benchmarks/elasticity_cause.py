"""Why the elasticity cycle needs more than 20 MG-PCG iterations on bunny and spot (issue 32): where its
slowest modes live, on a small hierarchy of each mesh.

Clamped elasticity (E = 1, lowest 5 % of x fixed) on the default 3-level hierarchy (the fine level a red
refinement of the input meshed by TetWild, then one nested cage), at ``--max-tets`` (default 40000).
Per mesh and ν:

``twogrid``  the fine level and level 1 alone, level 1 solved exactly, one or two symmetric Gauss–Seidel
             sweeps before and after (``sgs1``, ``sgs2``), or one sweep followed by a symmetric
             multiplicative Schwarz sweep over the fine dofs inside each level-1 tet that touches the
             boundary (``sgs1_schwarz``: exact 3x3-block solves of ~30 dofs per patch, pyamg's
             ``overlapping_schwarz_csr``): the largest eigenvalues of the error propagation (ARPACK, natural
             node order) and MG-PCG iterations to 1e-8 with that two-grid cycle.
             ``smoothing_cpu_seconds``: one smoothing step (median of 5, ``time.process_time``).
``slow_modes``  for the six slowest modes of ``sgs1``: fraction of their energy ``|e_i (A e)_i|`` on the
             boundary nodes, nodes holding 90 % of it, Rayleigh quotient ``eᵀAe / eᵀDe`` (small: smooth).
``cage``     level 1 and the cage alone (Galerkin operator of level 1, cage solved exactly), MG-PCG
             iterations with one and two sweeps.
``cycles``   MG-PCG iterations of the whole hierarchy: V-cycle 1 / 2 sweeps, W-cycle 2 / 4, each without
             and with two symmetric sweeps on the traction-free boundary nodes (``_local``).

::

    OMP_NUM_THREADS=1 python benchmarks/elasticity_cause.py ZOO_DIR/bunny.off ZOO_DIR/spot.obj \\
        --out benchmarks/results/elasticity/cause_small.json
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

SGS = "symmetric_gauss_seidel"


def _sgs(n: int) -> tuple[str, dict]:
    return (SGS, {"iterations": n})


def boundary_patches(P0, T1, n1: int, pos: np.ndarray):
    """Free dofs (interleaved) of the fine nodes inside each level-1 tet touching the boundary: the rows
    of the nodal ``P0`` whose support lies in the tet. Returns pyamg's ``(subdomain, subdomain_ptr)``."""
    import scipy.sparse as sp

    from solvers import block_dofs
    from solvers.fem import boundary_nodes

    on = np.zeros(n1, dtype=bool)
    on[boundary_nodes(T1, n=n1)] = True
    sel = np.flatnonzero(on[T1].any(axis=1))
    pat = sp.csr_matrix((np.ones(P0.nnz), P0.indices, P0.indptr), shape=P0.shape)
    C = sp.csr_matrix((np.ones(4 * len(sel)), (np.repeat(np.arange(len(sel)), 4), T1[sel].ravel())),
                      shape=(len(sel), n1))
    M = (C @ pat.T).tocsr()  # |support ∩ tet| per (tet, fine node)
    M.data = (M.data == np.diff(P0.indptr)[M.indices]).astype(float)
    M.eliminate_zeros()
    dofs, ptr = [], [0]
    for t in range(M.shape[0]):
        f = pos[M.indices[M.indptr[t]:M.indptr[t + 1]]]
        d = np.sort(block_dofs(f[f >= 0]))
        dofs.append(d)
        ptr.append(ptr[-1] + len(d))
    return np.concatenate(dofs).astype(np.int32), np.asarray(ptr, dtype=np.int32)


def twogrid(pr, P0_nodal, T1, n1, n0) -> dict:
    """Two-grid spectra and MG-PCG iterations (module docstring), and the slow modes of ``sgs1``."""
    import scipy.sparse.linalg as spla
    from pyamg import amg_core
    from pyamg.relaxation import relaxation

    from solvers.fem import boundary_nodes
    from solvers.krylov import pcg

    A = pr.A.tocsr()
    A.sort_indices()
    P = pr.P[0]
    lu = spla.splu((P.T @ A @ P).tocsc())
    pos = np.full(n0, -1)
    pos[pr.free[0]] = np.arange(len(pr.free[0]))
    sub, ptr = boundary_patches(P0_nodal.tocsr(), T1, n1, pos)
    sub, ptr, inv, iptr = relaxation.schwarz_parameters(A, sub, ptr)
    nsub = len(ptr) - 1

    def schwarz(x, b):
        for rng in ((0, nsub, 1), (nsub - 1, -1, -1)):
            amg_core.overlapping_schwarz_csr(A.indptr, A.indices, A.data, x, b, inv, iptr, sub, ptr, nsub,
                                             A.shape[0], *rng)

    def cycle(x, b, k, patch):
        relaxation.gauss_seidel(A, x, b, iterations=k, sweep="symmetric")
        if patch:
            schwarz(x, b)
        x += P @ lu.solve(P.T @ (b - A @ x))
        if patch:
            schwarz(x, b)
        relaxation.gauss_seidel(A, x, b, iterations=k, sweep="symmetric")

    out = {"patches": int(nsub)}
    zero = np.zeros(A.shape[0])
    vecs = None
    for name, k, patch in (("sgs1", 1, False), ("sgs2", 2, False), ("sgs1_schwarz", 1, True)):
        def E(v, k=k, patch=patch):
            x = np.array(v, dtype=np.float64)
            cycle(x, zero, k, patch)
            return x

        w, X = spla.eigs(spla.LinearOperator(A.shape, matvec=E, dtype=np.float64), k=8, which="LM", tol=1e-4)
        order = np.argsort(-np.abs(w))
        if name == "sgs1":
            vecs = np.real(X[:, order[:6]])

        def M(r, k=k, patch=patch):
            r = np.asarray(r, dtype=np.float64).reshape(-1)
            x = np.zeros_like(r)
            cycle(x, r, k, patch)
            return x

        res = pcg(A, pr.b, M=spla.LinearOperator(A.shape, matvec=M, dtype=np.float64), tol=1e-8, maxiter=300)
        x, secs = np.random.default_rng(0).standard_normal(A.shape[0]), []
        for _ in range(5):  # one smoothing step: the sweeps before the coarse correction
            t0 = time.process_time()
            relaxation.gauss_seidel(A, x, zero, iterations=k, sweep="symmetric")
            if patch:
                schwarz(x, zero)
            secs.append(time.process_time() - t0)
        out[name] = {"top_eigenvalues": [float(v) for v in np.abs(w[order])],
                     "pcg_iterations": int(res.iterations), "converged": bool(res.converged),
                     "smoothing_cpu_seconds": float(np.median(secs))}
    on = np.isin(pr.free[0], boundary_nodes(pr_tets[0][1], n=n0))  # free nodes on the boundary
    D = A.diagonal()
    modes = []
    for e in vecs.T:
        en = np.abs(e * (A @ e)).reshape(-1, 3).sum(axis=1)
        en /= en.sum()
        o = np.argsort(-en)
        modes.append({"energy_on_boundary": float(en[on].sum()),
                      "nodes_for_90pct": int(np.searchsorted(np.cumsum(en[o]), 0.9) + 1),
                      "rayleigh_vs_diagonal": float(e @ (A @ e) / (e @ (D * e)))})
    out["slow_modes"] = modes
    out["boundary_node_fraction"] = float(on.mean())
    return out


pr_tets: list = []


def run_mesh(spec: str, max_tets: int, nus) -> dict:
    """Every measurement of the module docstring on one mesh."""
    import nestmg
    from elasticity import load_surface
    from nestmg.elasticity import setup_elasticity
    from solvers import MultigridSolver

    V, F = load_surface(spec)
    h = nestmg.build_hierarchy(V, F, 3, "nested", sizing=nestmg.SizingOptions(max_tets=max_tets), cache=True,
                               progress=False)
    tets = h.tets_in("normalized")
    pr_tets[:] = tets
    T1, n1, n0 = np.asarray(tets[1][1]), len(tets[1][0]), len(tets[0][0])
    rec = {"mesh": Path(spec).name, "tets": [len(T) for _, T in tets], "cases": []}
    for nu in nus:
        pr = setup_elasticity(tets, h.P, "elasticity-clamped", nu=nu)
        case = {"nu": nu, "unknowns": int(pr.A.shape[0]), "twogrid": twogrid(pr, h.P[0], T1, n1, n0)}
        A1 = (pr.P[0].T @ pr.A @ pr.P[0]).tocsr()
        case["cage"] = {}
        for k in (1, 2):
            ml = MultigridSolver(A1, pr.P[1:], presmoother=[_sgs(k)], deflate=0, symmetric=True)
            case["cage"][f"sgs{k}"] = int(ml.solve(pr.P[0].T @ pr.b, tol=1e-8, accel="cg",
                                                   return_info=True)[1]["iterations"])
        case["cycles"] = {}
        for name, spec_, cyc in (("V12", [_sgs(1), _sgs(2)], "V"), ("W24", [_sgs(2), _sgs(4)], "W")):
            for local in (False, True):
                ml = pr.multigrid(presmoother=spec_, cycle=cyc, local_nodes=pr.local_nodes if local else None,
                                  local_sweeps=2)
                it = ml.solve(pr.b, tol=1e-8, accel="cg", return_info=True)[1]["iterations"]
                case["cycles"][name + ("_local" if local else "")] = int(it)
        print(f"{rec['mesh']} nu={nu}: {json.dumps(case)[:400]}", file=sys.stderr, flush=True)
        rec["cases"].append(case)
    return rec


def table(res: dict) -> str:
    """Markdown table of a result file: per mesh and ν, the two-grid's largest eigenvalue (MG-PCG
    iterations) per smoother, where its six slowest modes live, the cage level's two-grid iterations and the
    whole cycle's."""
    head = ("| mesh | fine tets | ν | two-grid sgs1 | sgs2 | sgs1 + Schwarz | slow modes: energy on boundary "
            "(boundary nodes) | Rayleigh | cage two-grid sgs1 / sgs2 | V 1/2 | V + boundary | W 2/4 "
            "| W + boundary |")
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for rec in res["meshes"]:
        for c in rec["cases"]:
            t = c["twogrid"]
            tg = [f"{t[k]['top_eigenvalues'][0]:.3f} ({t[k]['pcg_iterations']})"
                  for k in ("sgs1", "sgs2", "sgs1_schwarz")]
            en = [m["energy_on_boundary"] for m in t["slow_modes"]]
            ra = [m["rayleigh_vs_diagonal"] for m in t["slow_modes"]]
            cy = c["cycles"]
            lines.append(f"| {rec['mesh']} | {rec['tets'][0]:,} | {c['nu']} | " + " | ".join(tg)
                         + f" | {min(en):.2f}–{max(en):.2f} ({t['boundary_node_fraction']:.2f}) | "
                         f"{min(ra):.3f}–{max(ra):.3f} | {c['cage']['sgs1']} / {c['cage']['sgs2']} | "
                         + " | ".join(str(cy[k]) for k in ("V12", "V12_local", "W24", "W24_local")) + " |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("meshes", nargs="*")
    ap.add_argument("--table", type=Path, default=None, help="only print the Markdown table of this JSON")
    ap.add_argument("--max-tets", type=int, default=40_000)
    ap.add_argument("--nu", type=float, nargs="+", default=[0.3, 0.45])
    ap.add_argument("--out", type=Path, default=None)
    a = ap.parse_args(argv)
    if a.table is not None:
        print(table(json.loads(a.table.read_text())))
        return 0
    from exp_common import environment, git_commit, write_json

    res = {"command": "python benchmarks/elasticity_cause.py " + " ".join(
               [Path(m).name if not m.startswith("shape:") else m for m in a.meshes]
               + [f"--max-tets {a.max_tets}", "--nu"] + [str(v) for v in a.nu]),
           "commit": git_commit(), "environment": environment(),
           "params": {"max_tets": a.max_tets, "nu": a.nu},
           "meshes": [run_mesh(m, a.max_tets, a.nu) for m in a.meshes]}
    write_json(res, a.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
