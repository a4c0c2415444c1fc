#!/usr/bin/env bash
# Sets up everything mideepbasis needs, idempotently: a libLLVM that drjit 1.5 can use
# (LLVM 15 and 16 crash it; Debian 12 gets libllvm19 from apt), the virtual environment
# .venv/ in this folder (made with the quickest Python 3.11 here), and the package with its
# pinned dependencies and test tools.
set -euo pipefail
cd "$(dirname "$0")"

have_llvm() {
    ldconfig -p 2>/dev/null | grep -Eq 'libLLVM(-(1[7-9]|[2-9][0-9])\.so|\.so\.(1[7-9]|[2-9][0-9]))'
}

# The quickest Python 3.11 that can make a virtual environment. Interpreters differ: pyenv's
# default build (no profile-guided optimisation, a shared libpython) ran this project's Python half
# as fast as Debian's /usr/bin/python3.11, and every capture command 0.64 s slower (5.52 against
# 6.31 s: benchmarks/command_ab.py --before-python, benchmarks/README.md).
python_speed() {  # best of 3 of a fixed loop [s], or nothing when $1 is not a Python 3.11 with venv
    "$1" - <<'PYTHON' 2>/dev/null
import sys, time
if sys.version_info[:2] != (3, 11):
    sys.exit(1)
import ensurepip, venv  # noqa: F401  (Debian splits venv off into python3.11-venv)
def call(value):
    return value + 1
def work():  # calls, attributes, a dictionary and a module-level loop, as a package's Python does
    start, total, table = time.perf_counter(), 0, {}
    for index in range(100_000):
        total += call(index) + sys.maxsize.bit_length()
        table[index & 1023] = total
    exec("total = 0\nfor index in range(200_000): total += index", {})
    return time.perf_counter() - start
print(f"{min(work() for _ in range(3)):.4f}")
PYTHON
}

less_than() {  # whether the number $1 is below the number $2 (bash compares integers only)
    awk -v a="$1" -v b="$2" 'BEGIN { exit !(a < b) }'
}

choose_python() {  # prints the quickest Python 3.11 with venv found, or fails
    # Three rounds over the candidates in turn, each one's best kept: this machine's speed drifts
    # within seconds, and one round once ranked the slower interpreter first.
    local -a paths=() fastest=()
    local candidate path real reals=" " seconds index round python="" best=""
    for candidate in python3.11 /usr/bin/python3.11 /usr/local/bin/python3.11 python3; do
        path=$(command -v "$candidate" 2>/dev/null) || continue
        # Each file once, however many links lead to it (/usr/bin/python3 -> python3.11).
        real=$(realpath "$path")
        case "$reals" in *" $real "*) continue ;; esac
        reals="$reals$real "
        paths+=("$path") fastest+=("")
    done
    for round in 1 2 3; do
        for index in "${!paths[@]}"; do
            seconds=$(python_speed "${paths[$index]}") || continue
            if [ -z "${fastest[$index]}" ] || less_than "$seconds" "${fastest[$index]}"; then
                fastest[$index]=$seconds
            fi
        done
    done
    for index in "${!paths[@]}"; do
        [ -n "${fastest[$index]}" ] || continue
        if [ -z "$best" ] || less_than "${fastest[$index]}" "$best"; then
            python=${paths[$index]} best=${fastest[$index]}
        fi
    done
    if [ -z "$python" ]; then
        echo "setup: Python 3.11 with its venv module is required (Debian: apt-get install python3.11-venv)" >&2
        return 1
    fi
    echo "$python"
}

# ./setup.sh --which-python: the interpreter a new .venv would be made with, and nothing else.
if [ "${1:-}" = "--which-python" ]; then
    choose_python
    exit
fi

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

if [ ! -x .venv/bin/python ]; then
    python=$(choose_python)
    echo "setup: creating .venv with $python"
    "$python" -m venv .venv
fi
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
