# Sourced by the set-up scripts: create or reuse the virtual environment .venv inside the repo
# and install apo with the extras named in $APO_EXTRAS (e.g. "all"). Reinstalls only when
# pyproject.toml changed since the last install.
set -euo pipefail
repo="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$repo"
py="${PYTHON:-}"
if [ -z "$py" ]; then
  for cand in python3.11 python3; do
    if command -v "$cand" >/dev/null 2>&1; then py="$cand"; break; fi
  done
fi
[ -n "$py" ] || { echo "error: no python3.11 or python3 on PATH" >&2; exit 1; }
if [ ! -x .venv/bin/python ]; then
  echo "creating .venv with $py"
  "$py" -m venv .venv
fi
spec="."
[ -n "${APO_EXTRAS:-}" ] && spec=".[${APO_EXTRAS}]"
stamp=".venv/.apo-installed-$(echo "$spec" | tr -c 'a-z0-9' '_')"
want="$(sha256sum pyproject.toml | cut -d' ' -f1)"
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$want" ]; then
  echo "installing apo $spec into .venv (first run takes a few minutes)"
  .venv/bin/python -m pip install -q --upgrade pip
  .venv/bin/python -m pip install -q -e "$spec"
  echo "$want" > "$stamp"
fi
