#!/usr/bin/env bash
# Install the optional PETSc backend of nestmg (`solvers.petsc`, extra "petsc") on Debian/Ubuntu.
#
#   1. Debian's PETSc 3.18 (headers, libraries, Open MPI, hypre, PT-Scotch):  apt-get install petsc-dev
#   2. petsc4py 3.18.5 compiled against it. Debian's own python3-petsc4py is built for numpy 1.x and does
#      not import beside numpy 2, so we build petsc4py from source. Its setup.py needs setuptools<70;
#      we build the wheel in a throw-away venv (which sees this interpreter's numpy through
#      --system-site-packages) so the environment's own setuptools is never downgraded, then install
#      the wheel with the environment's pip.
#
# Idempotent: exits at once when `from petsc4py import PETSc` already works (set FORCE=1 to rebuild).
# Environment knobs: PYTHON (default: python), PETSC_DIR (default: Debian's real-scalar PETSc 3.18),
# PETSC4PY_VERSION (default 3.18.5, must match PETSc's major.minor).
set -euo pipefail

PYTHON="${PYTHON:-python}"
PETSC4PY_VERSION="${PETSC4PY_VERSION:-3.18.5}"

if [[ "${FORCE:-0}" != "1" ]] && "$PYTHON" -c "from petsc4py import PETSc" >/dev/null 2>&1; then
    echo "install-petsc: petsc4py already imports ($("$PYTHON" -c 'import petsc4py; print(petsc4py.__version__)')), nothing to do"
    exit 0
fi

SUDO=""
if [[ "$(id -u)" != "0" ]]; then
    command -v sudo >/dev/null 2>&1 || { echo "install-petsc: need root or sudo for apt-get" >&2; exit 1; }
    SUDO="sudo"
fi

if ! dpkg -s petsc-dev >/dev/null 2>&1; then
    echo "install-petsc: apt-get install petsc-dev"
    export DEBIAN_FRONTEND=noninteractive
    $SUDO apt-get install -y petsc-dev || { $SUDO apt-get update && $SUDO apt-get install -y petsc-dev; }
fi

if [[ -z "${PETSC_DIR:-}" ]]; then
    arch="$(dpkg-architecture -qDEB_HOST_MULTIARCH 2>/dev/null || echo x86_64-linux-gnu)"
    PETSC_DIR="/usr/lib/petscdir/petsc3.18/${arch}-real"
fi
[[ -f "$PETSC_DIR/include/petscconf.h" ]] || { echo "install-petsc: no PETSc at PETSC_DIR=$PETSC_DIR" >&2; exit 1; }
export PETSC_DIR
unset PETSC_ARCH  # Debian's PETSc is a prefix install

# petsc4py is built against, and imports, numpy: make sure this environment has it (a fresh venv may not)
if ! "$PYTHON" -c "import numpy" >/dev/null 2>&1; then
    echo "install-petsc: installing numpy into $("$PYTHON" -c 'import sys; print(sys.prefix)')"
    "$PYTHON" -m pip install --quiet "numpy>=1.24"
fi

build="$(mktemp -d)"
trap 'rm -rf "$build"' EXIT
echo "install-petsc: building petsc4py==$PETSC4PY_VERSION against $PETSC_DIR (about 2 minutes on 2 cores)"
if "$PYTHON" -m venv --system-site-packages "$build/venv" >/dev/null 2>&1; then
    # the build venv sees the base interpreter's site-packages, not a venv's: give it the target's numpy
    numpy_version="$("$PYTHON" -c 'import numpy; print(numpy.__version__)')"
    "$build/venv/bin/python" -m pip install --quiet cython "setuptools<70" wheel "numpy==$numpy_version"
    "$build/venv/bin/python" -m pip wheel --no-build-isolation --no-deps --quiet \
        -w "$build/wheels" "petsc4py==$PETSC4PY_VERSION"
    "$PYTHON" -m pip install --no-deps --force-reinstall "$build"/wheels/petsc4py-*.whl
else
    # no venv module (e.g. Debian without python3-venv): build in the environment itself. This pins
    # setuptools<70 there; projects built with build isolation (pip install .) are not affected.
    echo "install-petsc: no venv module, building in the environment (setuptools<70 will be installed)" >&2
    "$PYTHON" -m pip install --quiet cython "setuptools<70" wheel
    "$PYTHON" -m pip install --no-build-isolation --no-deps --force-reinstall "petsc4py==$PETSC4PY_VERSION"
fi

"$PYTHON" - <<'PY'
import petsc4py
from petsc4py import PETSc
pc = PETSc.PC().create(comm=PETSc.COMM_SELF)
pc.setType("hypre")  # raises if this PETSc has no hypre
print("install-petsc: petsc4py", petsc4py.__version__, "PETSc", "%d.%d.%d" % PETSc.Sys.getVersion(), "with hypre")
PY
command -v mpirun >/dev/null 2>&1 && echo "install-petsc: mpirun is $(command -v mpirun)" \
    || echo "install-petsc: warning, no mpirun on PATH (the MPI tests will be skipped)"
