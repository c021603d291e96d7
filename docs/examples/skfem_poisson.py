"""Your mesh, your matrix: scikit-fem assembles, nestmg's nested-cage hierarchy preconditions.

The fine level of :func:`nestmg.hierarchy_from_tets` is the caller's tet mesh, node for node, so a matrix
assembled by any FEM code on that mesh pairs with the hierarchy's prolongations ``H.P``:

* Dirichlet Poisson ``-Δu = f``, ``u = 0`` on the boundary: scikit-fem's P1 ``laplace`` restricted to the
  interior nodes, prolongations restricted with :func:`solvers.restrict_prolongations`; solved by nestmg's
  MG-preconditioned CG and by scipy's ``cg`` with ``M=ml.aspreconditioner()``.
* Neumann Poisson (singular, constant null space): the full matrix with ``H.P`` as it is.
* P2 elements: one more level on top, the exact P1 -> P2 interpolation on the same tets
  (:func:`nestmg.usermesh.p1_to_p2_prolongation`), then the P1 hierarchy.

Run ``python docs/examples/skfem_poisson.py`` (or ``main(V, T)`` with your own tet mesh).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse.linalg as spla
from skfem import Basis, BilinearForm, ElementTetP1, ElementTetP2, MeshTet, asm
from skfem.models.poisson import laplace, mass

from nestmg import hierarchy_from_tets, shapes, tetrahedralize
from nestmg.usermesh import p1_to_p2_prolongation
from solvers import MultigridSolver, restrict_prolongations


def source(x):
    """A smooth source f(x, y, z) = 1 + sin(3x) cos(2y) + z (scikit-fem passes (3, ...) coordinates)."""
    return 1.0 + np.sin(3 * x[0]) * np.cos(2 * x[1]) + x[2]


def scipy_cg_iterations(A, b, M, tol: float) -> tuple[np.ndarray, int]:
    """scipy's CG with preconditioner ``M``; returns the solution and the iteration count."""
    count = [0]

    def cb(_xk):
        count[0] += 1

    try:  # scipy >= 1.12 spells the tolerance rtol
        x, info = spla.cg(A, b, M=M, rtol=tol, maxiter=200, callback=cb)
    except TypeError:  # pragma: no cover - older scipy
        x, info = spla.cg(A, b, M=M, tol=tol, maxiter=200, callback=cb)
    if info != 0:
        raise RuntimeError(f"scipy cg did not converge (info={info})")
    return x, count[0]


def main(V=None, T=None, levels: int = 3, tol: float = 1e-8, p2: bool = True, verbose: bool = True) -> dict:
    """Assemble with scikit-fem on ``(V, T)`` (default: a TetWild mesh of a sphere) and solve with nestmg's MG.

    Returns
    -------
    dict
        ``hierarchy``, iteration counts (``dirichlet_mgpcg``, ``dirichlet_scipy_cg``, ``neumann_mgpcg``,
        ``p2_mgpcg``), relative residuals and the solutions.
    """
    if V is None:
        Vs, Fs = shapes.sphere(res=16)
        V, T = tetrahedralize(Vs, Fs, edge_length=0.06)     # stands in for the user's own mesh
    H = hierarchy_from_tets(V, T, levels)                         # H.tets[0] is (V, T), node for node

    mesh = MeshTet(np.asarray(V, float).T, np.asarray(T).T)       # scikit-fem: (3, n) nodes, (4, t) tets
    basis = Basis(mesh, ElementTetP1())                           # P1 dof i = node i
    K = asm(laplace, basis).tocsr()
    M = asm(mass, basis).tocsr()
    b = M @ source(mesh.p)
    out: dict = {"hierarchy": H}

    # Dirichlet: unknowns on the interior nodes; coarse levels keep the nodes their support reaches
    interior = basis.complement_dofs(mesh.boundary_nodes())
    Pf, _ = restrict_prolongations(H.P, interior)
    A = K[interior][:, interior]
    ml = MultigridSolver(A, Pf)
    x, r = ml.solve(b[interior], tol=tol, accel="cg", return_info=True)   # MG-PCG
    x_sp, it_sp = scipy_cg_iterations(A, b[interior], ml.aspreconditioner(), tol)
    u = np.zeros(mesh.nvertices)
    u[interior] = x
    out.update(dirichlet_mgpcg=r["iterations"], dirichlet_residual=r["residuals"][-1], dirichlet_scipy_cg=it_sp,
               u_dirichlet=u, scipy_vs_mg=float(np.linalg.norm(x_sp - x) / np.linalg.norm(x)))

    # Neumann: the singular matrix on every node, H.P as it is (rows sum to 1: constants reproduced)
    bn = b - M @ np.full(mesh.nvertices, b.sum() / M.sum())       # compatible: sum(bn) = 0
    mln = MultigridSolver(K, H.P, nullspace="constant")
    xn, rn = mln.solve(bn, tol=tol, accel="cg", return_info=True)
    out.update(neumann_mgpcg=rn["iterations"], neumann_residual=rn["residuals"][-1], u_neumann=xn)

    if p2:  # P2 on the same tets: the exact P1 -> P2 interpolation is one more (finest) level
        basis2 = Basis(mesh, ElementTetP2())
        K2 = asm(laplace, basis2).tocsr()
        b2 = asm(BilinearForm(lambda u, v, w: u * v), basis2) @ basis2.project(source)
        P21 = p1_to_p2_prolongation(mesh.nvertices, mesh.edges.T)
        interior2 = basis2.complement_dofs(basis2.get_dofs())
        Pf2, _ = restrict_prolongations([P21, *H.P], interior2)
        ml2 = MultigridSolver(K2[interior2][:, interior2], Pf2)
        _, r2 = ml2.solve(b2[interior2], tol=tol, accel="cg", return_info=True)
        out.update(p2_mgpcg=r2["iterations"], p2_residual=r2["residuals"][-1], p2_unknowns=len(interior2))

    if verbose:
        print(H)
        print(f"Dirichlet P1 ({len(interior)} unknowns): MG-PCG {out['dirichlet_mgpcg']} iterations, "
              f"scipy cg(M=MG) {it_sp} iterations")
        print(f"Neumann P1 ({mesh.nvertices} unknowns, singular): MG-PCG {out['neumann_mgpcg']} iterations")
        if p2:
            print(f"Dirichlet P2 ({out['p2_unknowns']} unknowns, P2 -> P1 -> cages): MG-PCG {out['p2_mgpcg']} "
                  "iterations")
    return out


if __name__ == "__main__":
    main()
