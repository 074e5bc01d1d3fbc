#!/usr/bin/env bash
# The kit for one allocation of a lent GPU machine (benchmarks/README.md, "On the lent GPU
# machine"), built under .lease/ (ignored) from ../shared/device/stage-wheels.sh's wheels:
# dm-control slimmed to what `dm_control.mjcf` needs (56 -> 1.6 MB), every wheel in one tar split
# into parts p1..pN of PART_MB (default 38) so that a part and the tracked tree (~20 MB) fit the 64
# MiB one call carries; the last part also holds install.sh and launch.sh, jobs.sh, poll.sh,
# collect.sh from this folder. With $BULBJAX_YCB_DIR set the YCB folder travels too (as ycb.tgz,
# ~26 MB: Fig. 5's jobs read it). Build it anew each session; each set of caches an earlier
# machine added, in a folder of its own (.lease/caches*/, collect.sh's pieces), gets a call of its
# own, printed below (carry the sets the jobs need: Ant's, Fig. 5's, ...).
#   bash benchmarks/lease/make_kit.sh     (needs PyPI; BULBJAX_SHARED: the shared folder)
set -euo pipefail
top=$(git rev-parse --show-toplevel)
cd "$top"
here="$top/benchmarks/lease"
shared=${BULBJAX_SHARED:-$top/../shared}
bash "$shared/device/stage-wheels.sh" dm-control dm-env dm-tree labmaze fast-simplification >/dev/null
w=$(mktemp -d)
cat .dev-wheels/part_*/part_* | tar x -C "$w"
rm -rf .dev-wheels
python3 - "$w"/dm_control-*.whl <<'PY'
"""Rewrite dm-control's wheel without other suites' assets (their RECORD lines dropped too)."""
import os, sys, zipfile
DROP = ("dm_control/locomotion/", "dm_control/suite/dog_assets/", "dm_control/mujoco/testing/",
        "dm_control/blender/")
src = sys.argv[1]
tmp = src + ".tmp"
with zipfile.ZipFile(src) as zin, zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED, compresslevel=9) as zout:
    for item in zin.infolist():
        if item.filename.startswith(DROP):
            continue
        data = zin.read(item)
        if item.filename.endswith(".dist-info/RECORD"):
            data = b"".join(l for l in data.splitlines(keepends=True) if not l.decode().startswith(DROP))
        zout.writestr(item, data)
os.replace(tmp, src)
PY
if [ -n "${BULBJAX_YCB_DIR:-}" ]; then
  tar czf "$w/ycb.tgz" -C "$(dirname "$BULBJAX_YCB_DIR")" "$(basename "$BULBJAX_YCB_DIR")"
fi
rm -rf .lease/p[0-9]* .lease/part_* && mkdir -p .lease  # .lease/caches*/ (carried caches) stay
(cd "$w" && tar cf - .) | split -b "${PART_MB:-38}M" - .lease/part_
rm -rf "$w"
n=0
for p in .lease/part_*; do n=$((n + 1)); mkdir -p ".lease/p$n"; mv "$p" ".lease/p$n/"; done
cp "$here"/install.sh "$here"/launch.sh "$here"/jobs.sh "$here"/poll.sh "$here"/collect.sh ".lease/p$n/"
du -sh .lease/p* | sed 's/^/  /'
cat <<MSG
calls (carry one part each, back to back):
  1..$((n - 1)): carry [".lease/pK"]: mkdir -p /tmp/stage && cp .lease/pK/* /tmp/stage/
MSG
for d in .lease/caches*/; do  # each set of caches an earlier machine added (collect.sh), a call each
  d=${d%/}
  if ls "$d"/caches*.tgz.* >/dev/null 2>&1; then
    echo "  then: carry [\"$d\"]: mkdir -p /tmp/stage && cp $d/* /tmp/stage/ ($(du -sh "$d" | cut -f1): an earlier machine's compile cache and Warp's kernels, which launch.sh unpacks)"
  fi
done
cat <<MSG
  $n: carry [".lease/p$n"]: mkdir -p /tmp/stage && cp .lease/p$n/* /tmp/stage/ && bash /tmp/stage/launch.sh "REPRODUCE FLAGS" && sleep 60 && bash /tmp/stage/poll.sh 150
  then: bash /tmp/stage/poll.sh 540 (timeout_s 600) until it says rc 0; last: bash /tmp/stage/collect.sh
MSG
