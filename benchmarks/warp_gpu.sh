#!/usr/bin/env bash
# One GPU command after ../shared/device/warp_parts.sh's two staging calls (warp.so in
# /root/wstage): installs the carried wheels (.whl, .wp3) and MuJoCo Warp, unpacks the robots
# carried in .assets (benchmarks/robots.py --pack), then runs "$@" with $MEN set to them.
#   carry [".whl", ".wp3", ".assets"];  command: bash benchmarks/warp_gpu.sh python3 ...
set -uo pipefail
if [ ! -f /tmp/site/warp/bin/warp.so ]; then
  cat /root/wstage/warp.so.xz.0* | xz -d > /tmp/warp.so \
    && python3 -m pip install -q --no-index --no-deps --no-compile --target /tmp/site .whl/*.whl .wp3/*.whl \
    && tar -xJf .wp3/warp_py.tar.xz -C /tmp/site && mv /tmp/warp.so /tmp/site/warp/bin/warp.so \
    || { echo "warp install failed"; exit 1; }
fi
# Warp's kernel cache from an earlier machine (`tar -C ~/.cache -c warp | xz | split -b 15M`,
# staged as /root/wstage/wcache.tar.xz.*) saves the kernels' cold compile (T1 115 s, G1 99 s).
if [ ! -d ~/.cache/warp ] && ls /root/wstage/wcache.tar.xz.* >/dev/null 2>&1; then
  mkdir -p ~/.cache && cat /root/wstage/wcache.tar.xz.* | xz -d | tar -x -C ~/.cache
fi
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1 MEN=/tmp/men
mkdir -p "$MEN" && for f in .assets/*.tar.xz; do tar -xJf "$f" -C "$MEN"; done
python3 -c "import jax, warp, mujoco; print('jax', jax.__version__, 'warp', warp.__version__, 'mujoco', mujoco.__version__, jax.devices()[0].device_kind)" 2>&1 | tail -1
"$@"
