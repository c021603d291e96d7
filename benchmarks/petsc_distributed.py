"""Distributed fine level (issue 33): memory per rank, communication and answers on 1, 2 and 4 ranks.

    OMP_NUM_THREADS=1 python benchmarks/petsc_distributed.py --ranks 1 2 4 --refine 2 \
        --out benchmarks/results/petsc/petsc_distributed.json

The input is a TetWild mesh of a procedural torus (``--mesh FILE`` for your own tet mesh); its coarse levels
(``hierarchy_from_tets``: the mesh, then tet-meshed nested cages) are built once here and saved; then, for
each rank count, ``mpirun -n p`` runs this script's worker, which is the driver
``docs/examples/petsc_distributed.py`` step by step (DMPlex from rank 0, PT-Scotch distribution,
``--refine`` parallel refinements, per-rank P1 assembly, ``PetscMultigrid.from_distributed``, MG-PCG) with
every rank recording its resident memory after each step (``/proc/self/statm``), its peak
(``getrusage`` maxrss), the bytes of its fine-level objects, and PETSc's message counts and bytes in
``MatPtAP`` and ``KSPSolve``. Answers: the solution of every run is matched by coordinates with the
1-rank one; a last 1-rank run dumps its (global) operators and the in-process ``MultigridSolver`` solves
the same hierarchy with the same cycle. Writes the JSON and prints the memory table.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
TIGHT = 1e-12  # second solve, for comparing solutions across rank counts


def _driver():
    spec = importlib.util.spec_from_file_location("petsc_distributed_example",
                                                  ROOT / "docs" / "examples" / "petsc_distributed.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _rss() -> int:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


def _peak() -> int:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def _events(PETSc, names) -> dict:
    out = {}
    for name in names:
        info = PETSc.Log.Event(name).getPerfInfo()
        out[name] = {"count": int(info["count"]), "messages": float(info["numMessages"]),
                     "bytes": float(info["messageLength"]), "reductions": float(info["numReductions"]),
                     "seconds": float(info["time"])}
    return out


def _mat_bytes(PETSc, M) -> int:
    """AIJ storage of this rank's rows: 8 + 4 bytes per allocated non-zero, 4 per row (PETSc's own memory
    figure is 0 in Debian's build, which logs no memory)."""
    info = M.getInfo(PETSc.Mat.InfoType.LOCAL)
    return int(info["nz_allocated"] * (8 + np.dtype(PETSc.IntType).itemsize) + 4 * M.getLocalSize()[0])


def _reset_peak() -> None:
    """Start a new peak (``VmHWM`` and getrusage's maxrss) at the current resident memory (Linux)."""
    with open("/proc/self/clear_refs", "w") as f:
        f.write("5")


def _fine_objects(PETSc, rss, X, tets, ldof, gidx, owned, bnd, A, P0, points) -> dict:
    """Bytes of this rank's fine-level objects."""
    dmplex = rss["mesh distributed and refined"] - rss["input mesh"]
    arrays = int(X.nbytes + tets.nbytes + ldof.nbytes + gidx.nbytes + owned.nbytes + bnd.nbytes)
    return {"DMPlex (rss delta of distribute + refine)": dmplex,
            "local mesh arrays (X, tets, dof maps)": arrays,
            "A (MPIAIJ, local)": _mat_bytes(PETSc, A), "P0 (MPIAIJ, local)": _mat_bytes(PETSc, P0),
            "points + b + x (local)": int(points.nbytes + 2 * 8 * len(points))}


def _coarse_objects(PETSc, mg) -> dict:
    """Bytes of this rank's coarse-level objects: its rows of P_1.., of the coarse operators, the coarsest."""
    pc = mg.ksp.getPC()
    nlev = len(mg.levels)
    interp = sum(_mat_bytes(PETSc, pc.getMGInterpolation(lev)) for lev in range(1, nlev - 1))
    ops = sum(_mat_bytes(PETSc, (pc.getMGCoarseSolve() if lev == 0 else pc.getMGSmootherDown(lev))
                         .getOperators()[0]) for lev in range(nlev - 1))
    coarsest = mg.levels[-1]
    return {"coarse prolongations (local rows)": interp, "coarse operators (local rows)": ops,
            "coarsest operator (gathered on every rank)": 12 * coarsest["nnz"] + 4 * coarsest["n"],
            # V (24 B), global ids (8 B) per node, T (32 B) per tet: held while locating
            "crop of the first coarse mesh (transient)":
                32 * (mg.location["crop_tets"] + mg.location["crop_nodes"])}


def _coarse_input(args) -> tuple:
    """What this rank passes to ``from_distributed`` and the bytes it holds for it beforehand."""
    if not args.arrays:
        return (args.worker,), 0  # the file: each rank reads its pieces
    h = _load_global(args.worker)  # the previous way: the whole coarse levels on every rank, as global arrays
    held = h["V1"].nbytes + h["T1"].nbytes
    held += sum(P.data.nbytes + P.indices.nbytes + P.indptr.nbytes for P in h["Ps"])
    return ((h["V1"], h["T1"]), h["Ps"]), int(held)


def _fine_level(PETSc, drv, args, rank: int, rss: dict) -> dict:
    """The driver's fine-level steps (DMPlex from rank 0, distribute, refine, assemble), memory recorded."""
    V0, T0 = np.zeros((0, 3)), np.zeros((0, 4), dtype=np.int64)
    if rank == 0:  # the input mesh (= the first coarse level), on rank 0 only, to start the DMPlex
        with np.load(args.worker) as z:
            V0, T0 = z["V1"], z["T1"]
    rss["input mesh"] = _rss()
    t = time.perf_counter()
    f = {"dm": drv.distribute(PETSc, V0, T0, args.refine)}
    del V0, T0
    rss["mesh distributed and refined"] = _rss()
    f["X"], f["tets"], f["bnd"] = drv.local_mesh(f["dm"])
    f["ldof"], f["gidx"], f["owned"] = drv.dof_numbering(PETSc, f["dm"], f["bnd"])
    rss["local mesh arrays"] = _rss()
    f["A"], f["b"], f["points"] = drv.assemble(PETSc, f["dm"], f["X"], f["tets"], f["ldof"], f["owned"],
                                               f["gidx"])
    f["seconds"] = time.perf_counter() - t
    rss["assembled"] = _rss()
    return f


def worker(args) -> None:
    """One MPI rank: the driver's steps with memory and communication recorded; writes rank<r>.json/.npz."""
    import petsc4py

    petsc4py.init([sys.argv[0]])
    from petsc4py import PETSc

    from solvers.petsc import PetscMultigrid

    PETSc.Log.begin()
    comm = PETSc.COMM_WORLD
    rank = comm.getRank()
    rss, peaks = {"start": _rss()}, {}
    coarse, held = _coarse_input(args)
    rss["coarse arrays"] = _rss()
    f = _fine_level(PETSc, _driver(), args, rank, rss)
    A, b, points = f["A"], f["b"], f["points"]
    peaks["fine level"] = _peak()
    _reset_peak()  # the set-up's own peak from here
    setup_events = ["MatPtAPSymbolic", "MatPtAPNumeric", "PCSetUp"]
    ptap0 = _events(PETSc, setup_events)
    mg = PetscMultigrid.from_distributed(A, points, *coarse)
    rss["hierarchy"] = _rss()
    peaks["hierarchy setup"] = _peak()
    _reset_peak()
    ptap1 = _events(PETSc, setup_events)
    ptap = {e: {q: ptap1[e][q] - ptap0[e][q] for q in ptap1[e]} for e in setup_events}
    P0 = mg.ksp.getPC().getMGInterpolation(len(mg.levels) - 1)
    solve0 = _events(PETSc, ["KSPSolve", "PCApply", "MatMult"])
    x, info = mg.solve(b.getArray(), tol=args.tol)
    solve1 = _events(PETSc, ["KSPSolve", "PCApply", "MatMult"])
    rss["solved"] = _rss()
    xt, info_t = mg.solve(b.getArray(), tol=TIGHT)
    peaks["solve"] = _peak()
    objects = _fine_objects(PETSc, rss, f["X"], f["tets"], f["ldof"], f["gidx"], f["owned"], f["bnd"], A, P0,
                            points)
    rec = {"rank": rank, "ranks": comm.getSize(), "mode": "arrays" if args.arrays else "file",
           "rows": len(points), "tets": len(f["tets"]), "rss": rss, "peaks": peaks,
           "peak": max(peaks.values()),
           "coarse_arrays_bytes": held, "fine_objects": objects, "coarse_objects": _coarse_objects(PETSc, mg),
           "ptap": ptap, "solve": {k: {q: solve1[k][q] - solve0[k][q] for q in solve1[k]} for k in solve1},
           "iterations": info["iterations"], "final_residual": info["final_residual"],
           "iterations_tight": info_t["iterations"], "final_residual_tight": info_t["final_residual"],
           "levels": info["levels"], "location": mg.location, "setup_seconds": mg.setup_seconds,
           "solve_seconds": info["solve_seconds"], "mesh_and_assembly_seconds": f["seconds"]}
    out = Path(args.outdir)
    (out / f"rank{rank}.json").write_text(json.dumps(rec))
    np.savez(out / f"rank{rank}.npz", points=points, x=x, xt=xt)
    if args.dump:  # 1 rank only: the whole hierarchy as scipy matrices, for the in-process solver
        _dump(PETSc, mg, A, b, out / "hierarchy.npz")
    mg.destroy()
    for obj in (A, b, f["dm"]):
        obj.destroy()


def _load_global(path) -> dict:
    """The whole coarse levels of a save_coarse_levels file, as global arrays (what --compare-arrays runs)."""
    import scipy.sparse as sp

    with np.load(path) as z:
        h = {k: z[k] for k in z.files}
    Ps = [sp.csr_matrix((h[f"P{k}_data"], h[f"P{k}_indices"], h[f"P{k}_indptr"]),
                        shape=tuple(h[f"P{k}_shape"])) for k in range(int(h["n_coarse"]))]
    return {"V1": h["V1"], "T1": h["T1"], "Ps": Ps}


def _csr(M):
    import scipy.sparse as sp

    ai, aj, av = M.getValuesCSR()
    return sp.csr_matrix((av, aj, ai), shape=M.getSize())


def _dump(PETSc, mg, A, b, path: Path) -> None:
    from solvers.petsc import save_operators

    if mg.comm_size != 1:
        raise SystemExit("--dump needs one rank")
    pc = mg.ksp.getPC()
    nlev = len(mg.levels)
    Ps = [_csr(pc.getMGInterpolation(nlev - 1 - k)) for k in range(nlev - 1)]
    save_operators(path, _csr(A), Ps, b=b.getArray())


def _mpirun(ranks: int, argv: list[str], log: Path) -> float:
    env = dict(os.environ, OMPI_ALLOW_RUN_AS_ROOT="1", OMPI_ALLOW_RUN_AS_ROOT_CONFIRM="1",
               OMP_NUM_THREADS="1",
               PYTHONPATH=os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])))
    cmd = ["mpirun", "-n", str(ranks), "--oversubscribe", sys.executable, __file__, *argv]
    t = time.perf_counter()
    with open(log, "w") as f:
        subprocess.run(cmd, check=True, env=env, stdout=f, stderr=subprocess.STDOUT, cwd=ROOT, timeout=3600)
    return time.perf_counter() - t


def _sorted_solution(d: Path, ranks: int, key: str) -> tuple[np.ndarray, np.ndarray]:
    parts = [np.load(d / f"rank{r}.npz") for r in range(ranks)]
    pts = np.concatenate([p["points"] for p in parts])
    x = np.concatenate([p[key] for p in parts])
    order = np.lexsort(pts.T[::-1])
    return pts[order], x[order]


def _inprocess(path: Path, tol: float) -> dict:
    """The in-process MultigridSolver on the dumped hierarchy, PCMG's cycle (symmetric GS, V(1,1), CG; no
    deflation and in the given order, as PCMG: the defaults since issue 31 reorder and deflate)."""
    from solvers.multilevel import MultigridSolver
    from solvers.petsc import load_operators

    h = load_operators(path)
    sgs = ("gauss_seidel", {"sweep": "symmetric", "iterations": 1})
    ml = MultigridSolver(h["A"], h["Ps"], presmoother=sgs, postsmoother=sgs, deflate=0, ordering=None)
    x, info = ml.solve(h["b"], tol=tol, accel="cg", return_info=True)
    return {"iterations": int(info["iterations"]), "x": x}


def launcher(args) -> int:
    from solvers.petsc import save_coarse_levels

    drv = _driver()
    doc = {"benchmark": "petsc_distributed", "command": " ".join(["python", "benchmarks/petsc_distributed.py",
                                                                   *sys.argv[1:]]),
           "refine": args.refine, "tol": args.tol, "tight_tol": TIGHT, "runs": []}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        t = time.perf_counter()
        V, T, Ps = drv.coarse_levels(args.mesh, args.levels, edge_length=args.edge_length)
        doc["input_mesh"] = {"nodes": len(V), "tets": len(T),
                             "source": args.mesh and Path(args.mesh).name or "procedural torus"}
        doc["coarse_levels_seconds"] = time.perf_counter() - t
        save_coarse_levels(tmp / "coarse.npz", V, T, Ps)
        del V, T, Ps
        ref = None
        modes = ["file"] + (["arrays"] if args.compare_arrays else [])
        for p in args.ranks:
            for mode in modes:
                d = tmp / f"p{p}_{mode}"
                d.mkdir()
                argv = ["--worker", str(tmp / "coarse.npz"), "--outdir", str(d), "--refine", str(args.refine),
                        "--tol", str(args.tol)] + (["--arrays"] if mode == "arrays" else [])
                wall = _mpirun(p, argv, d / "log.txt")
                recs = [json.loads((d / f"rank{r}.json").read_text()) for r in range(p)]
                run = {"ranks": p, "wall_seconds": wall, "per_rank": recs}
                pts, x = _sorted_solution(d, p, "xt")
                if ref is None:
                    ref = (pts, x)
                if not np.array_equal(pts, ref[0]):
                    raise SystemExit(f"{p} ranks: the fine nodes differ from the first run's")
                run["solution_vs_first_run"] = float(np.linalg.norm(x - ref[1]) / np.linalg.norm(ref[1]))
                doc["runs" if mode == "file" else "runs_arrays"] = doc.get(
                    "runs" if mode == "file" else "runs_arrays", []) + [run]
                peak = [r["peak"] >> 20 for r in recs]
                print(f"{p} ranks ({mode}): {wall:.1f} s, peak per rank {peak} MiB, "
                      f"iterations {recs[0]['iterations']}", flush=True)
        d = tmp / "dump"
        d.mkdir()
        _mpirun(1, ["--worker", str(tmp / "coarse.npz"), "--outdir", str(d), "--refine", str(args.refine),
                    "--tol", str(args.tol), "--dump"], d / "log.txt")
        inproc = _inprocess(d / "hierarchy.npz", args.tol)
        pts1, x1 = _sorted_solution(d, 1, "x")
        order = np.lexsort(np.load(d / "rank0.npz")["points"].T[::-1])
        doc["inprocess"] = {"iterations": inproc["iterations"],
                            "solution_vs_petsc_1rank": float(np.linalg.norm(inproc["x"][order] - x1)
                                                             / np.linalg.norm(x1))}
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(doc, indent=1))
    print(json.dumps(doc["inprocess"]), f"-> {args.out}")
    return 0


# ------------------------------------------------------------------------- tables (benchmarks/doc_tables.py)
MIB = 2.0**20


def _fine_bytes(rec: dict) -> int:
    """A rank's fine-level memory: the peak of its mesh + assembly steps over its memory before the mesh."""
    return rec["peaks"]["fine level"] - rec["rss"]["input mesh"]


def _setup_bytes(rec: dict) -> int:
    """A rank's hierarchy set-up memory (P₀, its crop of the coarse mesh, its coarse rows, PtAP, coarsest
    solve): the peak during ``from_distributed`` over the resident memory before it."""
    return rec["peaks"]["hierarchy setup"] - rec["rss"]["assembled"]


def _coarse_kib(rec: dict) -> float:
    """KiB of a rank's coarse-level objects after set-up (its rows of P_1.., of A_1.., the coarsest)."""
    c = rec["coarse_objects"]
    return sum(v for k, v in c.items() if "transient" not in k) / 1024


def memory_table(doc: dict) -> tuple[list[str], list[list]]:
    """Per rank count: tets and peak per rank, fine-level and set-up memory, coarse pieces (max over
    ranks)."""
    base = doc["runs"][0]
    f1 = max(_fine_bytes(r) for r in base["per_rank"]) * base["ranks"]
    t1 = doc["input_mesh"]["tets"]
    rows = []
    for run in doc["runs"]:
        recs, p = run["per_rank"], run["ranks"]
        fine = max(_fine_bytes(r) for r in recs)
        obj = {k: max(r["fine_objects"][k] for r in recs) for k in recs[0]["fine_objects"]}
        crop = max(r["location"]["crop_tets"] for r in recs)
        rows.append([p, f"{max(r['tets'] for r in recs):,}", f"{max(r['peak'] for r in recs) / MIB:.0f}",
                     f"{fine / MIB:.0f}", f"{fine * p / f1:.2f}",
                     f"{obj['DMPlex (rss delta of distribute + refine)'] / MIB:.0f}",
                     f"{obj['A (MPIAIJ, local)'] / MIB:.1f}", f"{obj['P0 (MPIAIJ, local)'] / MIB:.1f}",
                     f"{max(_setup_bytes(r) for r in recs) / MIB:.1f}",
                     f"{crop:,} ({crop / t1:.2f})", f"{max(_coarse_kib(r) for r in recs):,.0f}",
                     f"{recs[0]['iterations']}", f"{run['solution_vs_first_run']:.0e}"])
    head = ["ranks", "fine tets per rank (max)", "peak MiB per rank (max)", "fine-level MiB per rank (max)",
            "fine-level memory x p / 1-rank", "DMPlex MiB", "A MiB", "P₀ MiB", "hierarchy set-up MiB",
            f"coarse tets kept per rank (of {t1:,})", "coarse-level KiB per rank",
            "CG iterations (1e-8)", "solution vs 1 rank (1e-12 solves)"]
    return head, rows


def coarse_table(doc: dict) -> tuple[list[str], list[list]]:
    """Per rank count (max over ranks): the coarse levels read per rank from the file vs held whole on
    every rank as arrays (``--compare-arrays``): first-coarse tets kept, bytes, set-up memory, answers."""
    t1 = doc["input_mesh"]["tets"]
    rows = []
    for run, old in zip(doc["runs"], doc["runs_arrays"]):
        recs, olds = run["per_rank"], old["per_rank"]
        crop = max(r["location"]["crop_tets"] for r in recs)
        crop_kib = max(r["coarse_objects"]["crop of the first coarse mesh (transient)"] for r in recs) / 1024
        held = max(r["coarse_arrays_bytes"] for r in olds) / 1024
        rows.append([run["ranks"], f"{max(r['tets'] for r in recs):,}", f"{crop:,} ({crop / t1:.2f})",
                     f"{crop_kib:,.0f}", f"{max(_coarse_kib(r) for r in recs):,.0f}", f"{held:,.0f}",
                     f"{max(_setup_bytes(r) for r in recs) / MIB:.1f} / "
                     f"{max(_setup_bytes(r) for r in olds) / MIB:.1f}",
                     f"{max(r['peak'] for r in recs) / MIB:.0f} / {max(r['peak'] for r in olds) / MIB:.0f}",
                     f"{recs[0]['iterations']} / {olds[0]['iterations']}",
                     f"{old['solution_vs_first_run']:.0e}"])
    head = ["ranks", "fine tets per rank (max)", f"first-coarse tets kept per rank (of {t1:,})",
            "file: crop KiB per rank (while locating)", "file: coarse objects KiB per rank (after set-up)",
            "arrays: coarse levels KiB held on every rank", "set-up MiB per rank, file / arrays",
            "peak MiB per rank, file / arrays", "CG iterations, file / arrays",
            "arrays' solution vs the file's 1-rank (1e-12 solves)"]
    return head, rows


def comm_rows(doc: dict) -> list[dict]:
    """Per rank count: PtAP and per-CG-iteration message bytes and counts (mean per rank)."""
    out = []
    for run in doc["runs"]:
        recs, p = run["per_rank"], run["ranks"]
        its = recs[0]["iterations"]
        ptap = sum(r["ptap"][e]["bytes"] for r in recs for e in ("MatPtAPSymbolic", "MatPtAPNumeric")) / p
        setup = sum(r["ptap"]["PCSetUp"]["bytes"] for r in recs) / p
        cyc = sum(r["solve"]["KSPSolve"]["bytes"] for r in recs) / p / its
        msgs = sum(r["solve"]["KSPSolve"]["messages"] for r in recs) / p / its
        out.append({"ranks": p, "tets_per_rank": sum(r["tets"] for r in recs) / p, "ptap_bytes": ptap,
                    "setup_bytes": setup, "cycle_bytes": cyc, "cycle_messages": msgs,
                    "reductions": sum(r["solve"]["KSPSolve"]["reductions"] for r in recs) / p / its})
    return out


# Arrays of a coarse level's size (n_k entries) that from_distributed holds on every rank while it sets up
# (solvers/petsc_distributed.py), bytes per coarse node: the weights (8), the scatter's two vectors (16),
# the gathered owners and their copies (24), the numbering (free, owners of free, perm, inv, new ids: 40),
# the owner test (1), level 1's outcodes (1). Counted, not measured: a sum, so an upper bound of what is
# alive at once.
GLOBAL_BYTES_PER_COARSE_NODE = 90


def estimate(doc: dict, tets: float = 1e8, ranks: int = 64) -> dict:
    """Measured-model estimate of a ``tets``-tet solve on ``ranks`` ranks (the refinement ratio kept).

    Memory per rank = start-up (measured) + fine-level bytes per tet x tets per rank + hierarchy set-up
    bytes per tet x tets per rank (P₀, the rank's crop of the first coarse mesh and its coarse rows all
    grow with its share; both per-tet figures from the largest rank-count run) + the arrays of coarse-level
    size every rank holds during set-up (:data:`GLOBAL_BYTES_PER_COARSE_NODE` x all coarse nodes, the first
    coarse level grown with the fine one) + the coarsest operator (gathered on every rank, as measured).
    Communication per rank: halo volume scales with the surface of a rank's part,
    ``(tets per rank)^(2/3)``, from the largest rank-count run.
    """
    last = doc["runs"][-1]
    recs, p = last["per_rank"], last["ranks"]
    per_tet = max(_fine_bytes(r) / r["tets"] for r in recs)
    setup_per_tet = max(_setup_bytes(r) / r["tets"] for r in recs)
    start = max(r["rss"]["start"] for r in recs)
    ratio = tets / sum(r["tets"] for r in recs)  # the input (first coarse) mesh grows with the fine one
    levels = recs[0]["levels"]
    coarse_nodes = levels[1]["n"] * ratio + sum(L["n"] for L in levels[2:])  # deeper (cage) levels kept
    global_bytes = GLOBAL_BYTES_PER_COARSE_NODE * coarse_nodes
    coarsest = max(r["coarse_objects"]["coarsest operator (gathered on every rank)"] for r in recs)
    tpr = tets / ranks
    c = comm_rows(doc)[-1]
    scale = (tpr / c["tets_per_rank"]) ** (2.0 / 3.0)
    coarse = setup_per_tet * tpr + global_bytes + coarsest
    return {"tets": tets, "ranks": ranks, "tets_per_rank": tpr, "fine_bytes_per_tet": per_tet,
            "setup_bytes_per_tet": setup_per_tet, "start_bytes": start, "coarse_bytes": coarse,
            "setup_bytes": setup_per_tet * tpr, "global_bytes": global_bytes, "coarsest_bytes": coarsest,
            "first_coarse_tets": doc["input_mesh"]["tets"] * ratio, "coarse_nodes": coarse_nodes,
            "crop_tets_per_rank": doc["input_mesh"]["tets"] * ratio / ranks
            * max(r["location"]["crop_tets"] for r in recs) * p / doc["input_mesh"]["tets"],
            "fine_bytes": per_tet * tpr, "memory_per_rank": start + coarse + per_tet * tpr,
            "ptap_bytes_per_rank": c["ptap_bytes"] * scale, "cycle_bytes_per_rank": c["cycle_bytes"] * scale,
            "from_ranks": p, "surface_scale": scale}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--ranks", type=int, nargs="+", default=[1, 2, 4])
    ap.add_argument("--mesh", help="a tet mesh file (default: TetWild mesh of a procedural torus)")
    ap.add_argument("--edge-length", type=float, default=0.027,
                    help="TetWild edge factor of the default torus")
    ap.add_argument("--levels", type=int, default=3, help="levels of the input mesh's hierarchy")
    ap.add_argument("--refine", type=int, default=2, help="parallel refinements of the input mesh")
    ap.add_argument("--tol", type=float, default=1e-8)
    ap.add_argument("--out", default="bench_out/petsc_distributed.json")
    ap.add_argument("--compare-arrays", action="store_true",
                    help="also run every rank count with the whole coarse levels as arrays on every rank")
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    ap.add_argument("--arrays", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--outdir", help=argparse.SUPPRESS)
    ap.add_argument("--dump", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        worker(args)
        return 0
    return launcher(args)


if __name__ == "__main__":
    sys.exit(main())
