#!/usr/bin/env bash
# Download the NeuralRGBD synthetic scenes (Azinovic et al., CVPR 2022), as Co-SLAM's
# scripts/download_rgbd.sh does (not run in CI).  Check the licence on the NeuralRGBD project page
# (https://dazinovic.github.io/neural-rgbd-surface-reconstruction/) before redistributing anything.
# Usage: bash data_scripts/download_neural_rgbd.sh [DEST]
#   (default ${TSSLAM_DATA:-$HOME/datasets/tsslam_ref}/neural_rgbd_data)
# Result: DEST/<scene>/images/, depth_filtered/, poses.txt  -> load_sequence(DEST/<scene>) ('neural_rgbd').
# URL: the one used by Co-SLAM's script (verify before use).  The archive is tested and unpacked into a
# scratch folder first: a cut download exits non-zero and the next run resumes it; a damaged one restarts.
set -euo pipefail
source "$(dirname "$0")/fetch.sh"
case "${1:-}" in
  -h|--help) sed -n '2,9p' "$0" | cut -c3-; exit 0 ;;
  -*) echo "error: unknown option $1 (usage: bash data_scripts/download_neural_rgbd.sh [DEST])" >&2; exit 2 ;;
esac
DEST="${1:-${TSSLAM_DATA:-$HOME/datasets/tsslam_ref}/neural_rgbd_data}"
URL="http://kaldir.vc.in.tum.de/neural_rgbd/neural_rgbd_data.zip"
mkdir -p "$DEST"
if [ -d "$DEST/breakfast_room" ] && [ ! -e "$DEST.zip" ]; then echo "have $DEST"; exit 0; fi
fetch "$URL" "$DEST.zip"
if ! unzip -tq "$DEST.zip" > /dev/null; then echo "error: $DEST.zip is damaged; run the script again" >&2; exit 1; fi
# the archive's top level is the scene folders (Co-SLAM unzips it inside data/neural_rgbd_data)
rm -rf "$DEST.unpack"
unzip -q "$DEST.zip" -d "$DEST.unpack"
if [ ! -d "$DEST.unpack/breakfast_room" ]; then echo "error: $DEST.zip holds no breakfast_room/" >&2; exit 1; fi
for scene in "$DEST.unpack"/*; do
  rm -rf "${DEST:?}/$(basename "$scene")"
  mv "$scene" "$DEST"/
done
rm -rf "$DEST.unpack" "$DEST.zip"
echo "wrote $DEST (scenes used by Co-SLAM: breakfast_room complete_kitchen green_room grey_white_room"
echo "  morning_apartment thin_geometry whiteroom)"
