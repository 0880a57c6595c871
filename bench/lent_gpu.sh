#!/usr/bin/env bash
# The device check (bench/device_check.py) on a lent NVIDIA machine whose image has
# python3 and NVIDIA's driver but neither pyopencl nor an OpenCL vendor file, and no
# network. Prepare here, then run this from the repository root there:
#
#   echo /.whl/ >> .git/info/exclude; echo /.scn/ >> .git/info/exclude
#   python3 -m pip download --no-deps --only-binary=:all: --python-version 3.12 \
#       --implementation cp --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 \
#       --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 -d .whl \
#       pyopencl pytools platformdirs siphash24 trimesh rtree OpenImageIO
#   mkdir -p .scn && cp -r ../shared/scenes/. .scn/     # the shared scenes travel too
#   device run: bash bench/lent_gpu.sh [device_check.py arguments], carry [.whl, .scn]
#
# On the H200 (16 cores) the suite ran about 2,200 tests in 125 s on 15 workers, and the
# quick benches took 4, 7 and 19 s: within a lease of 15 minutes, for example
#   bash bench/lent_gpu.sh --out /tmp/dc --tests-timeout 300 --bench-timeout 60 \
#       --pytest-args "-n 14"; tar czf $OUT/dc.tgz -C /tmp dc
# ($OUT brings back 8 files at most: hence the archive).
#
# (pocl-binary-distribution is left out: its 58 MB wheel does not fit beside the rest.)
#
# `bash bench/lent_gpu.sh --run CMD...` does the same set-up, then runs CMD instead of the
# device check (say a bench with --device nvidia, or a few tests with --tb=long).
set -u
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
    --target /tmp/site .whl/*.whl || { echo "lent_gpu: the carried wheels did not install"; exit 1; }
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1
lib=$(ls /usr/local/nvidia/lib64/libnvidia-opencl.so.1 /usr/lib/x86_64-linux-gnu/libnvidia-opencl.so.1 \
      2>/dev/null | head -1)
[ -n "$lib" ] || { echo "lent_gpu: NVIDIA's OpenCL library (libnvidia-opencl.so.1) not found"; exit 1; }
mkdir -p /etc/OpenCL/vendors && echo "$lib" > /etc/OpenCL/vendors/nvidia.icd
export OCL_ICD_VENDORS=/etc/OpenCL/vendors
if [ -d .scn ]; then mkdir -p ../shared && rm -rf ../shared/scenes && cp -r .scn ../shared/scenes; fi
if [ "${1:-}" = --run ]; then shift; "$@"; exit $?; fi
python3 bench/device_check.py --device nvidia "$@"
