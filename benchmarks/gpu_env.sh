#!/usr/bin/env bash
# The project's Python environment on a lent GPU machine (the workplace's device tool), whose image has PyTorch,
# CUDA and most of nerfstudio's dependencies but not nerfstudio, and no network.
#
#   bash benchmarks/gpu_env.sh pack [FRAMES]
#                                      here: the missing packages, as Python 3.12 / x86-64 files, into
#                                      .device_site/site.tar.xz (xz, and without the parts that nothing here runs:
#                                      a call carries 64 MiB with the working tree), and the real capture with the
#                                      masks tracking-real needs into .device_site/real; with FRAMES, only the
#                                      videos' first FRAMES frames (and their masks), to fit the call with a larger
#                                      working tree
#   bash benchmarks/gpu_env.sh setup   there (carry .device_site): unpack into /tmp/site, install this checkout
#                                      into it (so that nerfstudio finds the plugin's entry points), and put the
#                                      capture, if packed, where the benchmarks look (../shared/data/real), and
#                                      this checkout's benchmarks into /tmp/bench; then `export
#                                      PYTHONPATH=/tmp/site:/tmp/bench PATH=/tmp/site/bin:$PATH` and run
#                                      `python3 -P -m benchmarks ...` (-P: not the checkout's gear_nerfstudio folder)
#
# The packages are those nerfstudio 1.1.5 imports when it trains and evaluates gear-nerf, at the versions of
# constraints.txt, less what the device image already has; fpsample is 0.3.3
# (nerfstudio only imports it, for splatfacto; 1.0.2 has no Python 3.12 file in the package index here).
set -euo pipefail
cd "$(dirname "$0")/.."
PACKAGES=(appdirs==1.4.4 av==18.1.0 defusedxml==0.7.1 dill==0.4.1 docstring_parser==0.18.0 fpsample==0.3.3
  gsplat==1.4.0 mediapy==1.2.7 msgspec==0.22.0 multiprocess==0.70.19 nerfacc==0.5.2 nerfstudio==1.1.5 pathos==0.3.5
  pox==0.3.7 ppft==1.7.8 pyquaternion==0.9.9 pytorch-msssim==1.0.0 rawpy==0.28.0 shtab==1.13.0 splines==0.3.0 tensorly==0.10.0
  torch_fidelity==0.4.0 typeguard==4.6.0 tyro==1.0.17 viser==0.2.7 websockets==17.4)
case "${1:-}" in
  pack)
    rm -rf .device_site && mkdir -p .device_site/site .device_site/real
    .venv/bin/python -m pip install -q --no-deps --no-compile --target .device_site/site --implementation cp \
      --python-version 3.12 --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 \
      --platform manylinux1_x86_64 --only-binary=:all: "${PACKAGES[@]}"
    # Not needed to train, track or evaluate, and over the size a call carries with the working tree: gsplat's
    # CUDA sources (splatfacto only), tensorly's sample data, the viewer's web client and icons (no viewer runs
    # there), rawpy (ns-process-data's camera raw files only; nerfstudio imports it when it loads, so `setup` puts an
    # empty module in its place).
    rm -rf .device_site/site/gsplat/cuda/csrc .device_site/site/tensorly/datasets/data .device_site/site/viser/client \
      .device_site/site/viser/_icons .device_site/site/rawpy .device_site/site/rawpy.libs
    tar cf - -C .device_site site | xz -9 -T2 >.device_site/site.tar.xz && rm -rf .device_site/site
    cp -r ../shared/data/real/panoptic_basketball_video .device_site/real/
    # The masks of the cameras that tracking-real clicks in and tracks into (cam13, cam20).
    mkdir -p .device_site/real/panoptic_basketball_video_masks
    cp -r ../shared/data/real/panoptic_basketball_video_masks/cam{13,20} .device_site/real/panoptic_basketball_video_masks/
    if [ -n "${2:-}" ]; then
      # Stream copy of FRAMES + 6 packets: the decoder returns frames 0..FRAMES-1 bit for bit as from the whole video
      # (checked on all 31 videos for FRAMES 30; with FRAMES + 1 a reordered B-frame near the cut came out wrong).
      for video in .device_site/real/panoptic_basketball_video/cam*.mp4; do
        .venv/bin/ffmpeg -v error -y -i "../shared/data/real/panoptic_basketball_video/$(basename "$video")" -c copy \
          -frames:v $(($2 + 6)) "$video.cut.mp4" && mv "$video.cut.mp4" "$video"
      done
      find .device_site/real/panoptic_basketball_video_masks -name '*.png' | while read -r mask; do
        [ "$((10#$(basename "$mask" .png)))" -lt "$2" ] || rm "$mask"
      done
    fi
    du -sh .device_site/*
    ;;
  setup)
    python3 -c "import tarfile; tarfile.open('.device_site/site.tar.xz').extractall('/tmp', filter='data')"
    python3 -m pip install -q --upgrade --no-deps --no-build-isolation --no-index --no-compile --target /tmp/site .
    mkdir -p /tmp/site/rawpy && touch /tmp/site/rawpy/__init__.py
    # pip --target writes no console scripts: the ns-* commands that the benchmarks run, as modules (-P: not the
    # checkout's own gear_nerfstudio folder, which lacks the installed package's method_configs and data_parsers).
    mkdir -p /tmp/site/bin
    printf '#!/bin/sh\nexec python3 -P -m nerfstudio.scripts.train "$@"\n' >/tmp/site/bin/ns-train
    printf '#!/bin/sh\nexec python3 -P -m gear_nerfstudio.tracking.cli "$@"\n' >/tmp/site/bin/ns-gear-track
    chmod +x /tmp/site/bin/ns-train /tmp/site/bin/ns-gear-track
    mkdir -p /tmp/bench && ln -sfn "$PWD/benchmarks" /tmp/bench/benchmarks
    if [ -d .device_site/real ]; then mkdir -p ../shared/data/real && cp -r .device_site/real/* ../shared/data/real/; fi
    ;;
  *)
    echo "usage: bash benchmarks/gpu_env.sh pack|setup" >&2
    exit 2
    ;;
esac
