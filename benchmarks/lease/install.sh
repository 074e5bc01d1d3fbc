# On the GPU machine: the wheels' parts in /tmp/stage into ${LEASE_ROOT:-/tmp}/site, the YCB
# folder (when the kit has it) into ${LEASE_ROOT:-/tmp}/ycb; nothing when no part is there.
set -e
R=${LEASE_ROOT:-/tmp}
cd "$R/stage"
ls part_* >/dev/null 2>&1 || { echo "install: no parts in $R/stage"; exit 0; }
mkdir -p w && cat part_* | tar x -C w
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target "$R/site" w/*.whl
if [ -f w/ycb.tgz ]; then rm -rf "$R/ycb" && mkdir -p "$R/ycb" && tar xzf w/ycb.tgz -C "$R/ycb" --strip-components=1; fi
rm -rf w part_*
echo "installed into $R/site ($(date -u +%T))"
