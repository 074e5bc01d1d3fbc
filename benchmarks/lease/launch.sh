# On the GPU machine, from the checkout's root (where a call runs): install the wheels, unpack
# caches brought from an earlier machine (caches.tgz.* beside the wheels, as collect.sh split
# them), copy the tree to $R/bj (a later call lays the tree again under anything that runs from
# it) and start jobs.sh detached with reproduce's flags "$1". LEASE_ROOT (default /tmp) moves it.
set -e
R=${LEASE_ROOT:-/tmp}
warp=${WARP_CACHE_DIR:-$HOME/.cache/warp}
bash "$R/stage/install.sh"
if ls "$R"/stage/caches.tgz.* >/dev/null 2>&1; then
  mkdir -p "$R/bjcache" && cat "$R"/stage/caches.tgz.* | tar xzf - -C "$R/bjcache"
  if [ -d "$R/bjcache/warp" ]; then mkdir -p "$(dirname "$warp")" && rm -rf "$warp" && mv "$R/bjcache/warp" "$warp"; fi
  echo "caches unpacked: $(du -sh "$R/bjcache" | cut -f1) compile cache, Warp's kernels in $warp"
fi
rm -rf "$R/bj" "$R/res" && mkdir -p "$R/bj" "$R/res"
tar --exclude=./.lease --exclude=./.venv --exclude=./.git --exclude=./runs -cf - . | tar -xf - -C "$R/bj"
date +%s > "$R/res/t0"
(ARGS="$1" setsid nohup bash "$R/stage/jobs.sh" > "$R/res/jobs.out" 2>&1 &)
echo "launched: bulbjax reproduce --out $R/res/paper $1"
