#!/usr/bin/env bash
# Main job: install apo (with the MuJoCo extra for the replay) into .venv and run the whole
# pipeline on the built-in example.
# Extra arguments go to `apo demo` (e.g. --out DIR, --seed N).
set -euo pipefail
APO_EXTRAS="sim" source "$(dirname "$0")/_venv.sh"
exec .venv/bin/apo demo "$@"
