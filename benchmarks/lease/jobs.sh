# The allocation's job: one `bulbjax reproduce` stretch (flags: $ARGS, quoted as in a shell) over
# a copy of the campaign's folder (less the runs in $DROP), from the installed wheel, GPU samples
# beside it. Writes $R/res/{reproduce.log,smi.csv,rc}.
R=${LEASE_ROOT:-/tmp}
export PYTHONPATH="$R/site${PYTHONPATH:+:$PYTHONPATH}" BULBJAX_CACHE_DIR="$R/bjcache"
[ -d "$R/ycb" ] && export BULBJAX_YCB_DIR="$R/ycb"
mkdir -p "$R/res" "$R/bjcache"
[ -d "$R/res/paper" ] || cp -r "$R/bj/docs/results/paper_h200" "$R/res/paper"
# DROP: finished runs to run again, paths under the plan folder (e.g. runs/fig2-cartpole/seed0,
# whose Fig. 4 needs the checkpoint that stayed on its machine)
for d in ${DROP:-}; do rm -rf "${R:?}/res/paper/$d" && echo "dropped $d: it runs again"; done
nvidia-smi --query-gpu=timestamp,index,utilization.gpu,memory.used --format=csv -l 15 > "$R/res/smi.csv" 2>&1 &
echo $! > "$R/res/smi.pid"
cd "$R"
eval "args=($ARGS)"
${LEASE_PYTHON:-python3} -m bulbjax reproduce --out "$R/res/paper" "${args[@]}" > "$R/res/reproduce.log" 2>&1
echo $? > "$R/res/rc"
kill "$(cat "$R/res/smi.pid")" 2>/dev/null
exit 0
