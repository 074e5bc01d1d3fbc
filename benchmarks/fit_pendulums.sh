#!/usr/bin/env bash
# Offline fits on the pendulums (issue 12): vae_rpl, svae, pred, dsa, 3 seeds, the fig2 presets'
# settings (multicolour 64x64 frames, lr 1e-4, 1,024-frame batches; 1,024 // 24 windows of 24
# steps for the sequential learners), bf16, a probe every 250 updates, on one cached
# random-policy dataset per env (256 worlds x 200 steps; 256 x 48 held out).
#
#   benchmarks/fit_pendulums.sh [ENV ...]      ENV: invpend, cartpole (default: both, one after the other)
#
# Environment: MAX_MINUTES (per env, default 7.5: `fit` stops cleanly before it and still probes
# and writes its plots), UPDATES (default 5000), OUT_ROOT (default docs/results), CACHE (default
# runs/cache), PYTHON (default .venv/bin/python if present, else python), EXTRA (more `fit`
# flags, e.g. the CPU smoke test's "--small --seeds 1 --data-worlds 8 ..."), RESUME=1 (continue the
# fits in OUT_ROOT from their checkpoints: 5,000 updates take two or three 10-minute calls on the
# same machine; UPDATES may grow). Without RESUME a fit starts afresh (--overwrite) over an earlier one.
# Writes OUT_ROOT/offline_<env>/{curves.jsonl,curves.png,table.md,recon.png,config.json}.
set -euo pipefail
cd "$(dirname "$0")/.."
MAX_MINUTES=${MAX_MINUTES:-7.5}
UPDATES=${UPDATES:-5000}
OUT_ROOT=${OUT_ROOT:-docs/results}
CACHE=${CACHE:-runs/cache}
if [ -z "${PYTHON:-}" ]; then
  if [ -x .venv/bin/python ]; then PYTHON=.venv/bin/python; else PYTHON=python; fi
fi
MODE=--overwrite  # a fresh fit replaces an earlier one in OUT_ROOT
[ -n "${RESUME:-}" ] && MODE=--resume
ENVS=("$@")
[ ${#ENVS[@]} -eq 0 ] && ENVS=(invpend cartpole)
for env in "${ENVS[@]}"; do
  case "$env" in
    invpend|cartpole) ;;
    *) echo "unknown env '$env' (invpend, cartpole)" >&2; exit 2 ;;
  esac
  # shellcheck disable=SC2086
  "$PYTHON" -m bulbjax.cli fit --preset "fig2-$env" --learners vae_rpl,svae,pred,dsa --seeds 3 \
    --updates "$UPDATES" --probe-every 250 --bf16 --max-minutes "$MAX_MINUTES" \
    --cache-dir "$CACHE" --out "$OUT_ROOT/offline_$env" "$MODE" ${EXTRA:-}
done
