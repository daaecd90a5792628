#!/usr/bin/env bash
# Brings a fresh machine up to what the project needs: the system libraries open3d
# loads at import time, then a virtual environment with the pinned Python packages.
# Last, it compiles the project's modules to bytecode and the tracker's numba code into numba's on-disk
# cache, so that no run does either.
# Idempotent: each step checks before it acts, so a second run costs a second or two.
# With --test it also installs what only the test suite needs (headless Chromium, which loads the
# HTML report to check that it renders).
set -euo pipefail
cd "$(dirname "$0")/.."

SYSTEM_PACKAGES=(libusb-1.0-0 libgl1 libegl1 libx11-6 libgomp1)
if [ "${1:-}" = "--test" ]; then
  SYSTEM_PACKAGES+=(chromium)
fi
missing=()
for pkg in "${SYSTEM_PACKAGES[@]}"; do
  dpkg -s "$pkg" >/dev/null 2>&1 || missing+=("$pkg")
done
if [ ${#missing[@]} -gt 0 ]; then
  echo "bootstrap: installing system packages: ${missing[*]}"
  SUDO=""
  [ "$(id -u)" -eq 0 ] || SUDO="sudo"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
fi

PYTHON=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  echo "bootstrap: creating .venv"
  "$PYTHON" -m venv .venv
fi
if [ ! -f .venv/.installed ] || [ pyproject.toml -nt .venv/.installed ] || [ requirements.lock -nt .venv/.installed ]; then
  echo "bootstrap: installing pinned Python packages (about a minute the first time)"
  # pip's own chatter (build-backend deprecation notices) goes to a log, shown only if it fails.
  log=.venv/pip-install.log
  if ! { .venv/bin/python -m pip install -q --disable-pip-version-check --upgrade pip &&
         .venv/bin/python -m pip install -q --disable-pip-version-check -c requirements.lock -e '.[dev]'; } >"$log" 2>&1; then
    cat "$log" >&2
    echo "bootstrap: pip install failed (log above, also in $log)" >&2
    exit 1
  fi
  touch .venv/.installed
fi

# The project's own modules to bytecode (__pycache__), as pip does for the packages it installs: the checkout is
# installed editable, and where Python may not write bytecode itself (PYTHONDONTWRITEBYTECODE, a read-only
# checkout) every run's processes would otherwise compile them from source as they start, about a tenth of a
# second each. A few hundredths of a second when nothing changed; a module edited since is compiled again here,
# and until then at each start, as without this step.
.venv/bin/python -m compileall -q pipeline stages calib ||
  echo "bootstrap: compiling the project's modules to bytecode failed; runs will compile them as they start" >&2

# The tracker's inner loops (stages/tracking/compiled.py) are compiled by numba on first use (20-30 s):
# compile them now into numba's cache (stages/tracking/__pycache__), with the types the tracking stage uses.
# A tenth of a second when its stamp there is fresh. A failure here only means the first run compiles.
.venv/bin/python -m pipeline warmup ||
  echo "bootstrap: compiling the tracker's code failed (above); the first run will compile it instead" >&2
