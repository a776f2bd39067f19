#!/usr/bin/env bash
# Test job: install apo with every extra into .venv, then lint, type-check and run the suite.
# Extra arguments go to pytest (e.g. -m "not slow", -k dof).
set -euo pipefail
APO_EXTRAS="all" source "$(dirname "$0")/_venv.sh"
# Open3D (perception extra) links against the system library libusb-1.0 on Debian/Ubuntu.
if ! .venv/bin/python -c "import open3d" >/dev/null 2>&1; then
  if ldconfig -p 2>/dev/null | grep -q libusb-1.0; then :; else
    if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
      echo "installing the system library libusb-1.0-0 for Open3D"
      apt-get update -qq && apt-get install -y -qq libusb-1.0-0 >/dev/null
    elif command -v sudo >/dev/null 2>&1 && command -v apt-get >/dev/null 2>&1; then
      sudo apt-get update -qq && sudo apt-get install -y -qq libusb-1.0-0 >/dev/null
    else
      echo "warning: Open3D cannot load libusb-1.0; install it (Debian: libusb-1.0-0)" >&2
    fi
  fi
fi
# The report's browser tests drive Debian's Chromium headless (tests/test_report_browser.py).
if ! command -v chromium >/dev/null 2>&1 || ! command -v chromedriver >/dev/null 2>&1; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
    echo "installing chromium and chromium-driver for the browser tests"
    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium chromium-driver >/dev/null \
      || echo "warning: could not install chromium; the browser tests will be skipped" >&2
  elif command -v sudo >/dev/null 2>&1 && command -v apt-get >/dev/null 2>&1; then
    sudo apt-get update -qq && sudo DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium chromium-driver >/dev/null \
      || echo "warning: could not install chromium; the browser tests will be skipped" >&2
  else
    echo "warning: no chromium/chromedriver; the browser tests will be skipped" >&2
  fi
fi
echo "== ruff check";  .venv/bin/ruff check src tests benchmarks
echo "== ruff format"; .venv/bin/ruff format --check src tests benchmarks
echo "== mypy";        .venv/bin/mypy
echo "== pytest"
exec .venv/bin/python -m pytest -n 2 "$@"
