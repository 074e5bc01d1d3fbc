# Into $OUT: the plan folder without checkpoints and the consoles (paper.tgz, in 15 MB pieces
# paper.tgz.aa, .ab, ...: a call brings back no file over 16 MiB, and Fig. 5's three seeds merged
# made it 22 MB; `cat paper.tgz.* | tar xzf -` on this side), and what this
# machine added to the compile cache and Warp's kernels since the launch (the sets carried here are
# already on the other side) as one set, caches-<launch time>.tgz in 15 MB pieces (caches/), for
# later machines: each set in a folder of its own under .lease/ (launch.sh merges the sets carried).
R=${LEASE_ROOT:-/tmp}
kill "$(cat "$R/res/smi.pid" 2>/dev/null)" 2>/dev/null
cd "$R/res" && tar czf "$R/paper.tgz" --exclude=checkpoints paper reproduce.log jobs.out smi.csv t0 $(ls rc 2>/dev/null)
split -b 15M "$R/paper.tgz" "$OUT/paper.tgz."
warp=${WARP_CACHE_DIR:-$HOME/.cache/warp}
new="$R/caches_new" && rm -rf "$new" && mkdir -p "$new/warp"
(cd "$R/bjcache" 2>/dev/null && find . -type f -newer "$R/res/t0" | tar cf - -T - | tar xf - -C "$new")
(cd "$warp" 2>/dev/null && find . -type f -newer "$R/res/t0" | tar cf - -T - | tar xf - -C "$new/warp")
name="caches-$(cat "$R/res/t0").tgz"
tar czf "$R/$name" -C "$new" .
s=$(stat -c %s "$R/$name")
if [ "$s" -lt 40000000 ]; then mkdir -p "$OUT/caches" && split -b 15M "$R/$name" "$OUT/caches/$name."
else echo "caches: $s bytes; bring them in a call of their own: mkdir -p \$OUT/caches && split -b 15M $R/$name \$OUT/caches/$name."; fi
ls -la "$OUT"
