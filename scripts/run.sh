#!/usr/bin/env bash
# Set up vsrd-mi on a fresh Debian/Ubuntu machine and run one of:
#   scripts/run.sh example   autolabel the bundled synthetic sequence (scenes/kitti360-synth), evaluate it
#   scripts/run.sh test      the default test suite (what CI runs)
# Set-up: Debian's libllvm19 (Dr.Jit's CPU backend; libLLVM 15 aborts Mitsuba), then the package.
set -euo pipefail
cd "$(dirname "$0")/.."
if ! ls /usr/lib/*/libLLVM.so.1[6-9]* /usr/lib/*/libLLVM-1[6-9]*.so* >/dev/null 2>&1; then
  SUDO=""; [ "$(id -u)" -eq 0 ] || SUDO="sudo"
  $SUDO apt-get update -qq && $SUDO apt-get install -y -qq libllvm19
fi
python3 -m pip install -q -e ".[test]"
case "${1:-}" in
  example)
    out=runs/example
    vsrd-mi autolabel scenes/kitti360-synth --sequence 0 --out "$out" --frames 14-14 "${@:2}"
    vsrd-mi eval --pred "$out" --gt scenes/kitti360-synth --sequence 0
    ;;
  test)
    python3 -m pytest -q "${@:2}"
    ;;
  *) echo "usage: scripts/run.sh example|test [extra args]" >&2; exit 2 ;;
esac
