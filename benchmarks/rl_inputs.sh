#!/usr/bin/env bash
# PPO on InvertedPendulum (multicolour) from the true state, from VAE_rpl's latent and from pixels
# (issue 15), 3 seeds each, the fig2-invpend preset's settings with VAE_rpl as the only learner;
# then one plot and table of the three return curves with the epochs each seed needed to reach 950.
#
#   benchmarks/rl_inputs.sh [KIND ...]     KIND: state, latent:vae_rpl, pixels (default: all three)
#
# Environment: MINUTES (per run, default 2.5: `run` stops cleanly after it), EPOCHS (default 400),
# OUT_ROOT (default docs/results/rl_inputs_invpend), PYTHON, EXTRA (more `run` flags). Each call
# regenerates the runs (--overwrite replaces those of an earlier call).
set -euo pipefail
cd "$(dirname "$0")/.."
MINUTES=${MINUTES:-2.5}
EPOCHS=${EPOCHS:-400}
OUT_ROOT=${OUT_ROOT:-docs/results/rl_inputs_invpend}
if [ -z "${PYTHON:-}" ]; then
  if [ -x .venv/bin/python ]; then PYTHON=.venv/bin/python; else PYTHON=python; fi
fi
KINDS=("$@")
[ ${#KINDS[@]} -eq 0 ] && KINDS=(state latent:vae_rpl pixels)
DIRS=()
for kind in "${KINDS[@]}"; do
  out="$OUT_ROOT/${kind//:/_}"
  # shellcheck disable=SC2086
  "$PYTHON" -m bulbjax.cli run --preset fig2-invpend --learners vae_rpl --seeds 3 --epochs "$EPOCHS" \
    --bf16 --rl-input "$kind" --max-minutes "$MINUTES" --out "$out" --overwrite ${EXTRA:-}
  DIRS+=("$out")
done
"$PYTHON" -m bulbjax.cli report --compare-rl "${DIRS[@]}" --out "$OUT_ROOT"
