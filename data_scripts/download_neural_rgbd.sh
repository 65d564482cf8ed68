#!/usr/bin/env bash
# Download the NeuralRGBD synthetic scenes (Azinovic et al., CVPR 2022), as Co-SLAM's
# scripts/download_rgbd.sh does (not run in CI).  Check the licence on the NeuralRGBD project page
# (https://dazinovic.github.io/neural-rgbd-surface-reconstruction/) before redistributing anything.
# Usage: bash data_scripts/download_neural_rgbd.sh [DEST]
#   (default ${TSSLAM_DATA:-$HOME/datasets/tsslam_ref}/neural_rgbd_data)
# Result: DEST/<scene>/images/, depth_filtered/, poses.txt  -> load_sequence(DEST/<scene>) ('neural_rgbd').
# URL: the one used by Co-SLAM's script (verify before use).
set -euo pipefail
DEST="${1:-${TSSLAM_DATA:-$HOME/datasets/tsslam_ref}/neural_rgbd_data}"
URL="http://kaldir.vc.in.tum.de/neural_rgbd/neural_rgbd_data.zip"
mkdir -p "$DEST"
if [ -d "$DEST/breakfast_room" ]; then echo "have $DEST"; exit 0; fi
curl -fL --retry 3 -o "$DEST.zip.part" "$URL"
mv "$DEST.zip.part" "$DEST.zip"
# the archive's top level is the scene folders (Co-SLAM unzips it inside data/neural_rgbd_data)
unzip -q "$DEST.zip" -d "$DEST" && rm "$DEST.zip"
echo "wrote $DEST (scenes used by Co-SLAM: breakfast_room complete_kitchen green_room grey_white_room"
echo "  morning_apartment thin_geometry whiteroom)"
