#!/usr/bin/env bash
# Download the Replica sequences of the NICE-SLAM release (Zhu et al., CVPR 2022; scenes from
# Straub et al. 2019, Replica licence: research use, see https://github.com/facebookresearch/Replica-Dataset).
# Not run in CI.  Usage: bash data_scripts/download_replica.sh [DEST]
#   (default ${TSSLAM_DATA:-$HOME/datasets/tsslam_ref}/Replica)
# Result: DEST/<scene>/results/frame%06d.jpg, depth%06d.png, traj.txt -> load_sequence(DEST/room0) ('replica').
# URL: the one used by NICE-SLAM's and Co-SLAM's download_replica.sh (verify before use).  The archive is
# tested and unpacked into a scratch folder first: a failed or cut download exits non-zero and the next
# run resumes it (data_scripts/fetch.sh); an archive that fails its test is fetched whole the next time.
set -euo pipefail
source "$(dirname "$0")/fetch.sh"
case "${1:-}" in
  -h|--help) sed -n '2,9p' "$0" | cut -c3-; exit 0 ;;
  -*) echo "error: unknown option $1 (usage: bash data_scripts/download_replica.sh [DEST])" >&2; exit 2 ;;
esac
DEST="${1:-${TSSLAM_DATA:-$HOME/datasets/tsslam_ref}/Replica}"
URL="https://cvg-data.inf.ethz.ch/nice-slam/data/Replica.zip"
mkdir -p "$DEST"
if [ -d "$DEST/room0/results" ] && [ ! -e "$DEST.zip" ]; then echo "have $DEST"; exit 0; fi
fetch "$URL" "$DEST.zip"
if ! unzip -tq "$DEST.zip" > /dev/null; then echo "error: $DEST.zip is damaged; run the script again" >&2; exit 1; fi
# the archive holds one folder, Replica/: unpack it beside DEST, then move its scenes into DEST
rm -rf "$DEST.unpack"
unzip -q "$DEST.zip" -d "$DEST.unpack"
if [ ! -d "$DEST.unpack/Replica" ]; then echo "error: $DEST.zip holds no Replica/ folder" >&2; exit 1; fi
for scene in "$DEST.unpack"/Replica/*; do
  rm -rf "${DEST:?}/$(basename "$scene")"
  mv "$scene" "$DEST"/
done
rm -rf "$DEST.unpack" "$DEST.zip"
echo "wrote $DEST"
