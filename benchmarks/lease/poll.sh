# Wait up to $1 seconds (default 500) for the stretch to end, then say where it stands.
R=${LEASE_ROOT:-/tmp}
t0=$(cat "$R/res/t0"); end=$(( $(date +%s) + ${1:-500} ))
while [ ! -f "$R/res/rc" ] && [ "$(date +%s)" -lt "$end" ]; do sleep 5; done
echo "elapsed since launch: $(( $(date +%s) - t0 )) s; rc: $(cat "$R/res/rc" 2>/dev/null || echo running)"
tail -n 12 "$R/res/reproduce.log"
tail -n 2 "$R/res/smi.csv" 2>/dev/null
f=$(ls -t "$R"/res/paper/runs/*/seed*/log.txt "$R"/res/paper/runs/*/*/seed*/log.txt 2>/dev/null | head -n 1)
[ -n "$f" ] && { echo "== $f"; tail -n 4 "$f"; }
exit 0
