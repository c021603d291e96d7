"""Linear elasticity on nested cages: a torus clamped at its lowest x under gravity, and the same torus free.

P1 vector elements (``solvers.elasticity_matrix``), prolongations ``P ⊗ I₃``, Galerkin coarse operators,
symmetric Gauss–Seidel (``multigrid(block=True)``: nodal 3x3 blocks); the free (pure traction) problem
keeps the six rigid-body modes out of every level. Run: ``python docs/examples/elasticity.py``
(docs/elasticity.md).
"""

import numpy as np

from nestmg import MeshingOptions, SizingOptions, build_hierarchy, shapes
from nestmg.elasticity import setup_elasticity


def main(max_tets: int = 200_000, mesher: str = "tetwild", nu: float = 0.3):
    V, F = shapes.torus(res=24)
    h = build_hierarchy(V, F, 3, "nested", sizing=SizingOptions(max_tets=max_tets),
                        meshing=MeshingOptions(mesher=mesher))
    tets = h.tets_in("normalized")  # unit bounding-box diagonal, as the command line poses its problems
    out = {}
    for name in ("elasticity-clamped", "elasticity-free"):
        prob = setup_elasticity(tets, h.P, name, E=1.0, nu=nu)  # K u = b, interleaved [x0, y0, z0, x1, ...]
        ml = prob.multigrid()  # MultigridSolver, or NullspaceMultigridSolver for the free problem
        x, info = ml.solve(prob.b, tol=1e-8, accel="cg", return_info=True)  # MG-preconditioned CG
        u = prob.expand(x)  # (n, 3) displacement of every fine node, 0 on the clamped ones
        print(f"{name}: {prob.A.shape[0]} unknowns, {info['iterations']} MG-PCG iterations, "
              f"max |u| = {np.abs(u).max():.3e}")
        out[name] = (prob, u, info)
    return h, out


if __name__ == "__main__":
    main()
