#!/usr/bin/env bash
# One-time set-up on a fresh Debian/Ubuntu machine: system packages, a virtual environment
# in .venv, and macroloc installed into it (editable). Idempotent: a second run is fast.
set -euo pipefail
cd "$(dirname "$0")/.."

# MACROLOC_EXTRAS: "runtime" (what `make demo` needs: no torch, no linters), "dev" (tests, the default), "dev,bench"...
EXTRAS=${MACROLOC_EXTRAS:-dev}
APT_PACKAGES=(libegl1 libegl-mesa0 libgl1-mesa-dri libgles2)  # EGL: headless rendering (the demo, the simulator)
[[ ",$EXTRAS," == *",bench,"* ]] && APT_PACKAGES+=(libusb-1.0-0)  # Open3D (the bench extra) loads libusb
missing=()
for p in "${APT_PACKAGES[@]}"; do
    dpkg -s "$p" >/dev/null 2>&1 || missing+=("$p")
done
if ((${#missing[@]})); then
    echo "setup: installing system packages: ${missing[*]}"
    SUDO=""; [ "$(id -u)" -eq 0 ] || SUDO="sudo"
    $SUDO apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}"
fi

PY=${PYTHON:-python3}
stamp=.venv/.setup-stamp
hash="$(sha256sum pyproject.toml | cut -c1-16)"
if [ -f "$stamp" ]; then
    read -r done_hash done_extras < "$stamp" || true
    # done when this pyproject was installed with these extras, or with any extras when only the runtime is asked
    if [ "$done_hash" = "$hash" ] && { [ "$done_extras" = "extras=$EXTRAS" ] || [ "$EXTRAS" = runtime ]; }; then
        exit 0
    fi
fi
[ -x .venv/bin/python ] || "$PY" -m venv .venv
.venv/bin/python -m pip install -q --upgrade pip
if [ "$EXTRAS" = runtime ]; then
    echo "setup: installing macroloc into .venv (first time: a few minutes)"
    .venv/bin/python -m pip install -q -e .
else
    echo "setup: installing macroloc[$EXTRAS] into .venv (first time: a few minutes)"
    .venv/bin/python -m pip install -q -e ".[$EXTRAS]"
fi
echo "$hash extras=$EXTRAS" > "$stamp"
echo "setup: done (.venv/bin/macroloc)"
