#!/usr/bin/env bash
# Install spdslam (editable) with its test extras and, when possible, CHOLMOD.
#
#   bash install.sh                  # uses python3
#   PYTHON=python3.12 bash install.sh
#
# 1. Ensures SuiteSparse headers (cholmod.h) and OpenBLAS are present: as root with apt-get it
#    installs Debian's libsuitesparse-dev and libopenblas0-pthread, otherwise it prints the
#    command to run and continues.
# 2. pip install -e ".[test,viewer,ros,ray,export,cholmod]"; if that fails (scikit-sparse cannot build),
#    falls back to pip install -e ".[test,viewer,ros,ray,export]", and the CHOLMOD bundled with cvxopt (a
#    default dependency) is used instead of scikit-sparse's. Either builds spdslam's compiled kernels
#    (geometry/_kernels.c) where a C compiler is there; without one spdslam uses its NumPy code.
# 3. Compiles spdslam's modules to bytecode (as pip does for a regular install).
# Safe to re-run; never prompts.
set -euo pipefail

PY="${PYTHON:-python3}"
export DEBIAN_FRONTEND=noninteractive
export PIP_DISABLE_PIP_VERSION_CHECK=1
export PIP_ROOT_USER_ACTION=ignore

cd "$(dirname "${BASH_SOURCE[0]}")"

say() { printf 'install.sh: %s\n' "$*"; }

# --- interpreter ---------------------------------------------------------------------------
if ! command -v "$PY" >/dev/null 2>&1; then
    say "error: Python interpreter '$PY' not found (set PYTHON=/path/to/python3.11+)" >&2
    exit 2
fi
if ! "$PY" -c 'import sys; sys.exit(0 if sys.version_info >= (3, 11) else 1)'; then
    say "error: spdslam needs Python >= 3.11; '$PY' is $("$PY" -c 'import platform; print(platform.python_version())')" >&2
    exit 2
fi
if ! "$PY" -m pip --version >/dev/null 2>&1; then
    say "pip missing for '$PY'; bootstrapping it with ensurepip"
    "$PY" -m ensurepip --upgrade
fi

# --- SuiteSparse headers (for scikit-sparse / CHOLMOD) ------------------------------------
have_cholmod_header() {
    local d
    for d in "${SUITESPARSE_INCLUDE_DIR:-}" /usr/include/suitesparse /usr/include \
             /usr/local/include/suitesparse /usr/local/include \
             "${CONDA_PREFIX:-}/include/suitesparse" "${CONDA_PREFIX:-}/include"; do
        [[ -n "$d" && -f "$d/cholmod.h" ]] && return 0
    done
    return 1
}

# Debian packages: SuiteSparse (CHOLMOD headers and libraries) and OpenBLAS, which Debian
# then selects as libblas.so.3: CHOLMOD's supernodal factorisation runs about 2x faster on
# it than on the reference BLAS.
missing=()
have_cholmod_header || missing+=(libsuitesparse-dev)
if command -v dpkg-query >/dev/null 2>&1 && \
   ! dpkg-query -W -f='${Status}' libopenblas0-pthread 2>/dev/null | grep -q "install ok installed"; then
    missing+=(libopenblas0-pthread)
fi
# A C compiler: scikit-sparse and spdslam's own kernels (geometry/_kernels.c) are compiled
# at install; without one the NumPy code is used (docs/install.md, "The compiled kernels").
if ! command -v cc >/dev/null 2>&1 && ! command -v gcc >/dev/null 2>&1; then
    missing+=(gcc libc6-dev)
fi
if [[ ${#missing[@]} -eq 0 ]]; then
    say "SuiteSparse headers (cholmod.h), OpenBLAS and a C compiler found"
elif [[ "$(id -u)" -eq 0 ]] && command -v apt-get >/dev/null 2>&1; then
    say "installing ${missing[*]} with apt-get"
    if apt-get update -qq && apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null; then
        say "${missing[*]} installed"
    else
        say "warning: apt-get could not install ${missing[*]}; continuing without"
    fi
else
    say "for CHOLMOD with a fast BLAS run: sudo apt-get install -y ${missing[*]} (Debian/Ubuntu). Continuing."
fi

# --- the package ---------------------------------------------------------------------------
if "$PY" -m pip install -q -e ".[test,viewer,ros,ray,export,cholmod]"; then
    say "installed spdslam with CHOLMOD (scikit-sparse)"
else
    say "pip install -e \".[test,viewer,ros,ray,export,cholmod]\" failed; retrying without scikit-sparse"
    "$PY" -m pip install -q -e ".[test,viewer,ros,ray,export]"
    say "NOTE: scikit-sparse is not installed; the CHOLMOD bundled with cvxopt will be used."
fi

# --- bytecode --------------------------------------------------------------------------------
# An editable install leaves spdslam's own modules uncompiled; where Python may not write
# __pycache__ (PYTHONDONTWRITEBYTECODE, a read-only checkout) every process would compile
# them again (about 0.35 s of each run). pip compiles a regular install; do the same here.
# A module edited later is recompiled from source (its .pyc no longer matches), never stale.
"$PY" -m compileall -q spdslam >/dev/null && say "compiled spdslam's modules to bytecode"

if "$PY" -c 'import sys; from spdslam.geometry import native; sys.exit(native.native_kernels() is None)' 2>/dev/null; then
    say "compiled kernels built (geometry/_kernels.c)"
else
    say "NOTE: the compiled kernels were not built (no C compiler?); spdslam uses its NumPy code"
fi

say "done; check with: spdslam info"
