#!/usr/bin/env bash
# mypy over the `macroloc.*` namespace. The packages live in top-level folders mapped by setuptools' package-dir,
# which mypy cannot follow through an editable install, so it reads them through a tree of links under build/.
set -euo pipefail
cd "$(dirname "$0")/.."
tree=build/typecheck/macroloc
mkdir -p "$tree"
for p in common graph perception proto service sim cli data; do ln -sfn "../../../$p" "$tree/$p"; done
cd build/typecheck
exec ../../.venv/bin/mypy --config-file ../../pyproject.toml -p macroloc "$@"
