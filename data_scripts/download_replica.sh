#!/usr/bin/env bash
# Download the Replica sequences of the NICE-SLAM release (Zhu et al., CVPR 2022; scenes from
# Straub et al. 2019, Replica licence: research use, see https://github.com/facebookresearch/Replica-Dataset).
# Not run in CI.  Usage: bash data_scripts/download_replica.sh [DEST]
#   (default ${TSSLAM_DATA:-$HOME/datasets/tsslam_ref}/Replica)
# Result: DEST/<scene>/results/frame%06d.jpg, depth%06d.png, traj.txt -> load_sequence(DEST/room0) ('replica').
# URL: the one used by NICE-SLAM's and Co-SLAM's download_replica.sh (verify before use).
set -euo pipefail
DEST="${1:-${TSSLAM_DATA:-$HOME/datasets/tsslam_ref}/Replica}"
URL="https://cvg-data.inf.ethz.ch/nice-slam/data/Replica.zip"
mkdir -p "$(dirname "$DEST")"
if [ -d "$DEST/room0/results" ]; then echo "have $DEST"; exit 0; fi
curl -fL --retry 3 -o "$DEST.zip.part" "$URL"
mv "$DEST.zip.part" "$DEST.zip"
# the archive holds one folder, Replica/: unpack it beside DEST, then move its scenes into DEST
mkdir -p "$DEST" "$DEST.unzip"
unzip -q "$DEST.zip" -d "$DEST.unzip"
mv "$DEST.unzip"/Replica/* "$DEST"/ && rm -r "$DEST.unzip" "$DEST.zip"
echo "wrote $DEST"
