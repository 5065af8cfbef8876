#!/usr/bin/env bash
# Regenerates CI's two constraint sets from pyproject.toml (needs uv: pip install uv).
#   oldest.txt: Python 3.11, every direct dependency at its lower bound (uv's lowest-direct
#               resolution), indirect ones at their newest except those held in oldest-fixes.txt;
#   newest.txt: the newest Python CI uses (3.13), the newest release of everything.
# The package's own metadata keeps ranges; only these files pin (README "Install").
set -euo pipefail
cd "$(dirname "$0")/.."
uv pip compile pyproject.toml --extra test --extra genicam --extra viewer --extra viewer-test --python-version 3.11 --resolution lowest-direct \
  --constraint constraints/oldest-fixes.txt --no-header --quiet -o constraints/oldest.txt
uv pip compile pyproject.toml --extra test --extra genicam --extra viewer --extra viewer-test --python-version 3.13 --no-header --quiet -o constraints/newest.txt
