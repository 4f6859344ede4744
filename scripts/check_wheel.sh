#!/usr/bin/env bash
# The installed package works on its own: build the wheel, install it (runtime dependencies only, no dev extras)
# into a fresh virtual environment, and run the demo from an unrelated folder. Run by CI after `make test`.
set -euo pipefail
cd "$(dirname "$0")/.."
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
.venv/bin/python -m pip wheel -q --no-deps --no-build-isolation -w "$work/dist" . > "$work/wheel.log" 2>&1 \
    || { cat "$work/wheel.log" >&2; exit 1; }
"${PYTHON:-python3}" -m venv "$work/venv"
"$work/venv/bin/python" -m pip install -q "$work"/dist/macroloc-*.whl > "$work/install.log" 2>&1 \
    || { cat "$work/install.log" >&2; exit 1; }
echo "check_wheel: runtime venv $(du -sm "$work/venv" | cut -f1) MB"
mkdir "$work/elsewhere" && cd "$work/elsewhere"
if "$work/venv/bin/python" -c "import torch" 2>/dev/null; then echo "check_wheel: torch is installed at run time" >&2; exit 1; fi
for name in graph perception service sim; do  # nothing top-level that could shadow (or be shadowed by) PyPI
    if [ -e "$work/venv/lib/python3"*/site-packages/$name ]; then echo "check_wheel: top-level '$name'" >&2; exit 1; fi
done
# lock-step: the simulated vehicle waits for each answer, so the flight is the same on a loaded CI machine
MACROLOC_CACHE="$work/cache" "$work/venv/bin/macroloc" demo --lockstep --out "$work/elsewhere/demo.png" \
    2> "$work/demo.err" | tail -3 || { tail -20 "$work/demo.err" >&2; exit 1; }
test -s demo.png
echo "check_wheel: wheel installed into a clean venv; 'macroloc demo' ran from $(pwd)"
