#!/usr/bin/env bash
# One-command set-up on a fresh Debian machine:
#   1. Debian's libllvm19 (Dr.Jit's LLVM backend; Debian 12's default 14/15 abort),
#   2. a virtual environment at .venv holding mi-invrgbl and its test tools,
#   3. the main job (skip with --no-run): render the example scene, generate the
#      synthetic street, import it, fit it and evaluate the fit.
set -euo pipefail
cd "$(dirname "$0")"

need_apt=()
ldconfig -p 2>/dev/null | grep -q 'libLLVM.so.19\|libLLVM-19' || need_apt+=(libllvm19)
python3 -c 'import ensurepip, venv' 2>/dev/null || need_apt+=(python3-venv)
if ((${#need_apt[@]})); then
  SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO=sudo
  echo "[setup] installing Debian packages: ${need_apt[*]}"
  $SUDO apt-get update -qq
  $SUDO apt-get install -y -qq "${need_apt[@]}"
fi

[ -x .venv/bin/python ] || python3 -m venv .venv
.venv/bin/python -m pip install -q --upgrade pip
.venv/bin/python -m pip install -q -e '.[test]'
echo "[setup] installed mi-invrgbl into .venv"

if [ "${1:-}" != "--no-run" ]; then
  .venv/bin/mi-invrgbl render scenes/street.xml -o out/street --overwrite
  [ -f out/street_data/gt/trajectory.json ] || .venv/bin/mi-invrgbl make-scene street out/street_data
  # Imported every time (5 s): a scene imported by an earlier release would keep its options.
  .venv/bin/mi-invrgbl import out/street_data -o out/street_fit/scene.xml --max-points 60000 --no-triangulate --roughness 0.85 --overwrite
  .venv/bin/mi-invrgbl fit out/street_fit/scene.xml --budget 8 --diffuse-fresnel --weights lidar2rgb=1 --overwrite
  .venv/bin/mi-invrgbl eval out/street_fit/fit
fi
