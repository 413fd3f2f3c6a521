#!/usr/bin/env bash
# Install everything prtbench needs on a fresh machine of this kind (Debian + CPython 3.11).
# Idempotent: a second run installs nothing new.  Called by `make setup` (and so by `make bench`
# and `make test`).
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}

# 1. A libLLVM that Dr.Jit's LLVM backend can use (>= 17 in practice; Debian's 15 crashes).
if ! ls /usr/lib/x86_64-linux-gnu/libLLVM*.so.* 2>/dev/null | grep -qE 'libLLVM(-|\.so\.)(1[7-9]|2[0-9])'; then
  if [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null; then
    echo "[setup] installing libllvm19 for Mitsuba's llvm_ad_rgb variant"
    (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libllvm19) \
      || echo "[setup] WARNING: libllvm19 could not be installed; Mitsuba falls back to scalar_rgb"
  else
    echo "[setup] WARNING: no libLLVM >= 17 and not root; Mitsuba falls back to scalar_rgb"
  fi
fi

# 1b. Debian's chromium, for the headless-browser test of the HTML report
#     (tests/reports/test_html_report.py; the test is skipped without it).
if ! command -v chromium >/dev/null 2>&1 && [ ! -x /usr/bin/chromium ]; then
  if [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null; then
    echo "[setup] installing chromium for the HTML report's headless-browser test"
    (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium) \
      || echo "[setup] WARNING: chromium could not be installed; the report's browser test will be skipped"
  else
    echo "[setup] WARNING: no chromium and not root; the report's browser test will be skipped"
  fi
fi

# 2. Python packages.  torch is pinned to the CPU build that lies on this machine's disk; it is
#    installed first and alone so nothing else can pull a CUDA build.  (This machine kind runs as root, and pip
#    then warns on every call that a virtual environment is recommended: the setup installs into the machine's
#    Python on purpose. Older pips ignore the variable.)
export PIP_ROOT_USER_ACTION=ignore
$PY -m pip install -q --disable-pip-version-check "torch==2.13.0"
$PY -m pip install -q --disable-pip-version-check -e ".[dev]"
echo "[setup] done"
