#!/usr/bin/env bash
# The installed package works on its own: build the wheel, install it (runtime dependencies only, no dev extras)
# into a fresh virtual environment, and run the demo from an unrelated folder. Run by CI after `make test`.
set -euo pipefail
cd "$(dirname "$0")/.."
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
.venv/bin/python -m pip wheel -q --no-deps --no-build-isolation -w "$work/dist" . 2>&1 | grep -v "^WARNING: Location" || true
"${PYTHON:-python3}" -m venv "$work/venv"
"$work/venv/bin/python" -m pip install -q "$work"/dist/macroloc-*.whl 2>&1 | grep -v "^WARNING: Location" || true
mkdir "$work/elsewhere" && cd "$work/elsewhere"
if "$work/venv/bin/python" -c "import torch" 2>/dev/null; then echo "check_wheel: torch is installed at run time" >&2; exit 1; fi
for name in graph perception service sim; do  # nothing top-level that could shadow (or be shadowed by) PyPI
    if [ -e "$work/venv/lib/python3"*/site-packages/$name ]; then echo "check_wheel: top-level '$name'" >&2; exit 1; fi
done
MACROLOC_CACHE="$work/cache" "$work/venv/bin/macroloc" demo --speedup 4 --out "$work/elsewhere/demo.png" | tail -5
test -s demo.png
echo "check_wheel: wheel installed into a clean venv; 'macroloc demo' ran from $(pwd)"
