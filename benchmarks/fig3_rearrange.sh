#!/usr/bin/env bash
# The `fig3-rearrange-geom` run (issues 10, 11 and 37) in stretches on one GPU machine: the frame
# VAEs (vae, vae_rpl, beta_vae, bf16) beside SPAIR 4x4 and 6x6 (fp32) on ReacherRearrangeGeom
# (the fixed black-background scene; PRESET=fig3-rearrange-geom-random: every world drawing one of
# the 12 versions per episode; PRESET=fig5-rearrange-ycb: VAE_rpl and SPAIR on RearrangeYcb), 3 seeds, probes every 5 epochs,
# reconstruction / SPAIR box figures every RECON epochs and at the end of each stretch.
#
#   benchmarks/fig3_rearrange.sh            # first call starts the run, later calls resume it
#
# Each call runs one stretch of at most LIMIT seconds (default 570, under a 10-minute call):
# the run stops itself after MAX_MINUTES (default 8; checked before each epoch) and checkpoints on
# the machine's disk; `timeout` ends a stretch still compiling at LIMIT (the persistent compile
# cache keeps what was compiled, so the next call gets further). A call that finds a checkpoint
# in RUN resumes from it. Then RUN without its checkpoints is packed into OUT/fig3.tgz (when OUT
# is set) so that the metrics, plots and figures survive the machine.
# Environment: PRESET (default fig3-rearrange-geom), RUN (default runs/fig3_rearrange_geom), MAX_MINUTES, LIMIT, RECON (default 100),
# EPOCHS (default: the preset's 1,000), PYTHON (default .venv/bin/python if present, else python3),
# EXTRA (more `run` flags for a fresh start, e.g. "--small --seeds 1" for a CPU smoke test).
set -uo pipefail
cd "$(dirname "$0")/.."
PRESET=${PRESET:-fig3-rearrange-geom}
RUN=${RUN:-runs/fig3_rearrange_geom}
MAX_MINUTES=${MAX_MINUTES:-8}
LIMIT=${LIMIT:-570}
RECON=${RECON:-100}
if [ -z "${PYTHON:-}" ]; then
  if [ -x .venv/bin/python ]; then PYTHON=.venv/bin/python; else PYTHON=python3; fi
fi
mkdir -p "$RUN"
n=$(find "$RUN" -maxdepth 1 -name 'stretch_*.log' | wc -l)
if [ -n "$(ls -A "$RUN/checkpoints" 2>/dev/null)" ]; then
  args=(--resume "$RUN")
else
  # shellcheck disable=SC2206
  # no checkpoint: nothing to resume, so start afresh over what an earlier stretch left (--overwrite)
  args=(--preset "$PRESET" --bf16 --probe-every 5 --out "$RUN" --overwrite ${EXTRA:-})
fi
[ -n "${EPOCHS:-}" ] && args+=(--epochs "$EPOCHS")
timeout -k 15 "$LIMIT" "$PYTHON" -m bulbjax run "${args[@]}" --max-minutes "$MAX_MINUTES" \
  --recon-every "$RECON" 2>&1 | grep --line-buffered -v "Warp\|Module " | tee "$RUN/stretch_$n.log"
rc=${PIPESTATUS[0]}
echo "stretch $n: exit $rc"
if [ -n "${OUT:-}" ]; then
  tar czf "$OUT/fig3.tgz" --exclude=checkpoints -C "$(dirname "$RUN")" "$(basename "$RUN")"
  ls -la "$OUT"
fi
exit "$rc"
