# On the GPU machine, from the checkout's root (where a call runs): install the wheels, unpack
# the caches brought from earlier machines (each set's pieces caches*.tgz.* beside the wheels, as
# collect.sh split them; several sets merge), copy the tree to $R/bj (a later call lays the tree
# again under anything that runs from it) and start jobs.sh detached with reproduce's flags "$1".
# LEASE_ROOT (default /tmp) moves it.
set -e
R=${LEASE_ROOT:-/tmp}
warp=${WARP_CACHE_DIR:-$HOME/.cache/warp}
bash "$R/stage/install.sh"
sets=$(ls "$R"/stage/caches*.tgz.aa 2>/dev/null | sed 's/\.aa$//')
for set in $sets; do  # each set: an earlier machine's additions (collect.sh), its pieces .aa, .ab, ...
  mkdir -p "$R/bjcache" && cat "$set".* | tar xzf - -C "$R/bjcache"
  if [ -d "$R/bjcache/warp" ]; then mkdir -p "$warp" && cp -rp "$R/bjcache/warp/." "$warp/" && rm -rf "$R/bjcache/warp"; fi
done
[ -n "$sets" ] && echo "caches unpacked ($(echo $sets | wc -w) set(s)): $(du -sh "$R/bjcache" | cut -f1) compile cache, Warp's kernels in $warp"
rm -rf "$R/bj" "$R/res" && mkdir -p "$R/bj" "$R/res"
tar --exclude=./.lease --exclude=./.venv --exclude=./.git --exclude=./runs -cf - . | tar -xf - -C "$R/bj"
date +%s > "$R/res/t0"
(ARGS="$1" setsid nohup bash "$R/stage/jobs.sh" > "$R/res/jobs.out" 2>&1 &)
echo "launched: bulbjax reproduce --out $R/res/paper $1"
