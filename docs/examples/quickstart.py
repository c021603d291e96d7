"""Quick start: a Neumann Poisson problem on a torus, multigrid with nested cages as coarse levels."""

from nestmg import MeshingOptions, build_hierarchy, setup_problem, shapes


def main(method: str = "nested", mesher: str = "tetwild"):
    V, F = shapes.torus(res=24)                                   # closed triangle mesh (V, F)
    h = build_hierarchy(V, F, 3, method, meshing=MeshingOptions(mesher=mesher))  # cages -> tets -> P_k
    prob = setup_problem(h.tets, h.P, "poisson-neumann")          # K u = M f, zero-mean f
    ml = prob.multigrid()  # solvers.MultigridSolver: V(1,1), boundary-layer sweeps, 2 coarse sweeps
    residuals = []
    u = ml.solve(prob.b, tol=1e-8, residuals=residuals)           # V(1,1) cycles
    print(h)
    print(ml)
    print(f"{len(residuals) - 1} V-cycles, final relative residual {residuals[-1]:.1e}")
    return h, u, residuals


if __name__ == "__main__":
    main()
