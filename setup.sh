#!/usr/bin/env bash
# Sets up everything mideepbasis needs, idempotently: a libLLVM that drjit 1.5 can use
# (LLVM 15 and 16 crash it; Debian 12 gets libllvm19 from apt), the virtual environment
# .venv/ in this folder, and the package with its pinned dependencies and test tools.
set -euo pipefail
cd "$(dirname "$0")"

have_llvm() {
    ldconfig -p 2>/dev/null | grep -Eq 'libLLVM(-(1[7-9]|[2-9][0-9])\.so|\.so\.(1[7-9]|[2-9][0-9]))'
}

if ! have_llvm && [ -z "${DRJIT_LIBLLVM_PATH:-}" ]; then
    if command -v apt-get >/dev/null 2>&1; then
        sudo=""
        [ "$(id -u)" -ne 0 ] && command -v sudo >/dev/null 2>&1 && sudo="sudo"
        echo "setup: installing libllvm19 for drjit's LLVM backend"
        $sudo apt-get install -y -q libllvm19 >/dev/null 2>&1 \
            || { $sudo apt-get update -q >/dev/null && $sudo apt-get install -y -q libllvm19 >/dev/null; }
    else
        echo "setup: no libLLVM 17 or newer found; install LLVM 19 and set DRJIT_LIBLLVM_PATH" >&2
        exit 1
    fi
fi

python=python3.11
command -v "$python" >/dev/null 2>&1 || python=python3
"$python" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))' \
    || { echo "setup: Python 3.11 is required (found $("$python" --version 2>&1))" >&2; exit 1; }

[ -x .venv/bin/python ] || "$python" -m venv .venv
# torch is pinned to the CPU build 2.13.0 (an unpinned torch pulls gigabytes of CUDA packages).
log=$(mktemp)
if ! .venv/bin/python -m pip install -q --disable-pip-version-check -e ".[test]" >"$log" 2>&1; then
    grep -v "^WARNING: Location" "$log" >&2; rm -f "$log"
    echo "setup: pip could not install the package (see above)" >&2; exit 1
fi
rm -f "$log"
# pip compiles the dependencies' modules; an editable install leaves the package's own to each
# import, which compiles them again every run where bytecode is not written
# (PYTHONDONTWRITEBYTECODE): 0.35 s of every command here.
.venv/bin/python -m compileall -q mideepbasis >/dev/null
.venv/bin/python -c "import mideepbasis.render" \
    || { echo "setup: the package does not import; see the error above" >&2; exit 1; }
echo "setup: ready (.venv)"
