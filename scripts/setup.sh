#!/usr/bin/env bash
# Set up a machine: a virtual environment in .venv with the CPU build of torch first, then the
# package in editable mode with its dev extras (the notebook runner; JupyterLab is the
# `notebooks` extra).
#
# torch is always the CPU build, asked for by name (torch==2.13.0+cpu): on Linux a plain
# `pip install torch` fetches the CUDA build and several GB of NVIDIA libraries. Where pip's
# configured sources hold that wheel (a find-links folder or a mirror, as on this project's
# machines) it comes from there, offline; elsewhere (an ordinary Linux machine) from PyTorch's
# CPU index, $TORCH_CPU_INDEX. macOS: PyPI's torch has no CUDA, so plain torch==2.13.0.
#
# The rest of the requirements go through uv (from PyPI, itself installed with pip) where it
# installs, else pip: uv downloads and installs in parallel (a fresh set-up 45 s against 108 s,
# idle: docs/development.md); GC_INSTALLER=pip forces pip. Debian's PostgreSQL and Compose
# client install in the background meanwhile.
#
# GC_SETUP_DRY_RUN=1 prints the install commands instead of running them. Sourced
# (`. scripts/setup.sh`), it defines its functions and runs nothing (tests/test_setup_script.py).
set -euo pipefail

TORCH_VERSION=2.13.0
TORCH_CPU_INDEX=${TORCH_CPU_INDEX:-https://download.pytorch.org/whl/cpu}

# Run a command with a time limit where coreutils' timeout exists (not on stock macOS).
with_timeout() {
  local seconds=$1
  shift
  if command -v timeout >/dev/null; then timeout "$seconds" "$@"; else "$@"; fi
}

# Succeed when pip's configured sources hold the requirement $1: a resolution that installs
# nothing (--dry-run), bounded so that an unreachable index cannot hang the set-up.
torch_findable() {
  with_timeout "${GC_PROBE_TIMEOUT:-120}" python -m pip install --dry-run --no-deps \
    --ignore-installed --quiet --retries 0 --timeout 20 "$1" >/dev/null 2>&1
}

# The arguments of `pip install` that install the CPU build of torch, one a line.
# $1: the operating system (default: uname -s).
torch_install_args() {
  local os=${1:-$(uname -s)}
  if [ "$os" != Linux ]; then
    echo "torch==$TORCH_VERSION"
  elif torch_findable "torch==$TORCH_VERSION+cpu"; then
    echo "torch==$TORCH_VERSION+cpu"
  else
    # the CPU index holds nothing else: any local label (+cpu on x86_64) is a CPU build
    printf '%s\n' --index-url "$TORCH_CPU_INDEX" --timeout 60 "torch==$TORCH_VERSION"
  fi
}

# Succeed when uv answers in this environment, installing it with pip if need be (a dry run
# only asks).
uv_ready() {
  python -m uv --version >/dev/null 2>&1 ||
    { [ "${GC_SETUP_DRY_RUN:-0}" != 1 ] && python -m pip install -q uv >/dev/null 2>&1; }
}

# Install the package in editable mode with its dev extras: through uv (bytecode compiled, as
# pip does) unless GC_INSTALLER=pip or uv is unavailable or fails; then through pip.
install_project() {
  if [ "${GC_INSTALLER:-uv}" = uv ] && uv_ready; then
    if run python -m uv pip install -q --python "$(command -v python)" --compile-bytecode -e '.[dev]'; then
      return 0
    fi
    echo "uv could not install the requirements; trying pip" >&2
  fi
  run python -m pip install -q -e '.[dev]'
}

# Run "$@", or print it under GC_SETUP_DRY_RUN=1.
run() {
  if [ "${GC_SETUP_DRY_RUN:-0}" = 1 ]; then echo "+ $*"; else "$@"; fi
}

main() {
  cd "$(dirname "${BASH_SOURCE[0]}")/.."
  local python=${PYTHON:-python3}
  if [ ! -x .venv/bin/python ]; then
    run "$python" -m venv .venv
  fi
  if [ -x .venv/bin/python ]; then
    . .venv/bin/activate
  fi
  # PostgreSQL's server programs, for the multi-worker Optuna tests (tests/pg.py starts a
  # throw-away cluster), and a Compose client, for the test that validates docker/compose.yaml
  # (no engine needed): no-ops when installed, else apt-get, beside the Python installs.
  # Without them those tests fail and say why.
  # Their own process group (set -m): a signal to the set-up stops them too; a failed
  # install waits for them (an apt-get is not cut short).
  services="" bg=""  # global: the EXIT trap reads them
  if [ "${GC_SETUP_DRY_RUN:-0}" != 1 ]; then
    services=$(mktemp)
    set -m
    {
      bash scripts/postgres.sh || echo "warning: PostgreSQL is missing; the PostgreSQL tests will fail"
      bash scripts/compose.sh || echo "warning: no Compose client; tests/test_docker.py will fail"
    } >"$services" 2>&1 &
    bg=$!
    set +m
    trap 'kill -TERM -- "-$bg" 2>/dev/null; exit 130' INT TERM
    trap 'wait; rm -f "$services"' EXIT
  fi
  if ! python -c "import torch, sys; sys.exit(torch.__version__.split('+')[0] != '$TORCH_VERSION')" 2>/dev/null; then
    local args
    mapfile -t args < <(torch_install_args)
    run python -m pip install -q "${args[@]}"
  fi
  install_project
  if [ "${GC_SETUP_DRY_RUN:-0}" = 1 ]; then
    return
  fi
  wait "$bg"
  cat "$services" >&2
  echo "setup done: $(python -c 'import torch; print("torch", torch.__version__)')"
}

if [ "${BASH_SOURCE[0]}" = "$0" ]; then
  main "$@"
fi
