#!/usr/bin/env bash
# Builds the folders that experiments/gpu_run.sh carries to a GPU machine (Python 3.12, no package registry there):
#   .wa/site_small.tar.xz  mujoco 3.17.0 (without its filament renderer, studio UI, tests and test data), mujoco-mjx,
#                          trimesh, quadprog, evosax, dotmap, eiquadprog and Eigen's headers (cmeel-eigen, without
#                          its unsupported/ modules: the force QP's CPU engine), unpacked and xz-packed;
#   .wb/wpart_00, .wc/wpart_01, .wd/wpart_02  the three thirds of an xz tar of the warp-lang 1.18.0 wheel's contents
#                          without its CPU compiler (warp-clang.so), examples and tests.
#   .wr/viz.tar.xz         (with --viz) rerun-sdk 0.41.0 without its viewer binary (the SDK records to files; its
#                          native bindings stripped of symbols) and the notebook runner (nbformat, nbclient, ipykernel
#                          and what they need that the GPU image lacks), for the gpu set's rerun and notebook tests:
#                          about 45 MB, so a call of its own on a held machine (.ci/nightly gpu; results/nightly/).
# A device call carries 64 MiB with the working tree: each call to a fresh machine carries .wa, one warp third and the
# race's state (.ws/); three calls on one held machine collect Warp. All these folders are git-ignored.
#
#   bash experiments/gpu_wheels.sh          # .wa .wb .wc .wd; needs pip with access to PyPI, xz, unzip
#   bash experiments/gpu_wheels.sh --viz    # .wr alone (also strip)
set -euo pipefail
cd "$(dirname "$0")/.."
W=$(mktemp -d); trap 'rm -rf "$W"' EXIT
PLAT=(--only-binary=:all: --python-version 3.12 --implementation cp --platform manylinux_2_28_x86_64
      --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64)
if [ "${1:-}" != "--viz" ]; then  # --viz builds .wr/ alone
python3 -m pip download -q --no-deps "${PLAT[@]}" -d "$W/whl" mujoco==3.17.0 quadprog==0.1.14 warp-lang==1.18.0 \
  eiquadprog==1.3.2
python3 -m pip download -q --no-deps -d "$W/whl" mujoco-mjx==3.17.0 trimesh==5.2.0 evosax==0.3.2 dotmap==1.3.30 \
  cmeel-eigen==3.4.1
mkdir -p "$W/site" "$W/warp" .wa .wb
for w in "$W"/whl/*.whl; do
  case "$(basename "$w")" in warp_lang*) unzip -q -o "$w" -d "$W/warp" ;; *) unzip -q -o "$w" -d "$W/site" ;; esac
done
rm -rf "$W/site/mujoco/experimental" "$W/site/mujoco/mjx/test_data" "$W/site/mujoco"/_render_filament*.so
find "$W/site" -name '*_test.py' -delete
rm -rf "$W/site/cmeel.prefix/include/eigen3/unsupported" "$W/site/cmeel.prefix/share"
rm -rf "$W/warp/warp/bin/warp-clang.so" "$W/warp/warp/examples" "$W/warp/warp/tests"
tar -cf - -C "$W/site" . | xz -T0 -6 > .wa/site_small.tar.xz
tar -cf - -C "$W/warp" . | xz -T0 -6 > "$W/warp.tar.xz"
split -n 3 -d -a 2 "$W/warp.tar.xz" "$W/wpart_"
mkdir -p .wc .wd; mv "$W/wpart_00" .wb/; mv "$W/wpart_01" .wc/; mv "$W/wpart_02" .wd/
du -sh .wa/* .wb/* .wc/* .wd/*
fi
if [ "${1:-}" = "--viz" ]; then
  # pure-Python and binary needs of the notebook runner and rerun that the GPU image (device KINDS.md) lacks
  python3 -m pip download -q "${PLAT[@]}" -d "$W/viz" rerun-sdk==0.41.0 nbformat==5.11.1 nbclient==0.11.0 ipykernel
  mkdir -p "$W/vsite" .wr
  for w in "$W"/viz/*.whl; do
    case "$(basename "$w")" in
      numpy-*|pillow-*|pyarrow-*|packaging-*|psutil-*|pygments-*|python_dateutil-*|typing_extensions-*|attrs-*|tzdata-*) ;;
      *) unzip -q -o "$w" -d "$W/vsite" -x 'rerun_cli/*' ;;
    esac
  done
  strip --strip-unneeded "$W"/vsite/rerun_bindings/*.so
  tar -cf - -C "$W/vsite" . | xz -T0 -6 > .wr/viz.tar.xz
  du -sh .wr/*
fi
