# Into $OUT: the plan folder without checkpoints and the consoles (paper.tgz), and the compile
# cache with Warp's kernels in 15 MB pieces (caches/) for a later machine of the same session.
R=${LEASE_ROOT:-/tmp}
kill "$(cat "$R/res/smi.pid" 2>/dev/null)" 2>/dev/null
cd "$R/res" && tar czf "$OUT/paper.tgz" --exclude=checkpoints paper reproduce.log jobs.out smi.csv t0 $(ls rc 2>/dev/null)
warp=${WARP_CACHE_DIR:-$HOME/.cache/warp}
tar czf "$R/caches.tgz" -C "$R/bjcache" . $( [ -d "$warp" ] && echo "-C $(dirname "$warp") $(basename "$warp")" ) 2>/dev/null
s=$(stat -c %s "$R/caches.tgz")
if [ "$s" -lt 40000000 ]; then mkdir -p "$OUT/caches" && split -b 15M "$R/caches.tgz" "$OUT/caches/caches.tgz."
else echo "caches: $s bytes; bring them in a call of their own: mkdir -p \$OUT/caches && split -b 15M $R/caches.tgz \$OUT/caches/caches.tgz."; fi
ls -la "$OUT"
