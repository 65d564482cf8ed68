#!/usr/bin/env bash
# Download TUM RGB-D sequences used by Co-SLAM / TS-SLAM (not run in CI).
#   fr1/desk, fr2/xyz, fr3/long_office_household  (Sturm et al., IROS 2012; CC BY 4.0)
# Usage: bash data_scripts/download_tum.sh [DEST]   (default ${TSSLAM_DATA:-$HOME/datasets/tsslam_ref}/TUM)
# Each sequence lands in DEST/rgbd_dataset_freiburgN_NAME/ with rgb.txt, depth.txt, groundtruth.txt:
# the layout `tsslam_ref.data.load_sequence` reads; the camera (fr1/fr2/fr3) comes from the folder name.
# URLs: the TUM download server (verify before use; the older host vision.in.tum.de is tried second).
# A sequence is unpacked into a scratch folder and moved into place only when the archive is whole, so
# a cut download exits non-zero and the next run resumes it; a damaged archive is fetched whole again.
set -euo pipefail
source "$(dirname "$0")/fetch.sh"
case "${1:-}" in
  -h|--help) sed -n '2,9p' "$0" | cut -c3-; exit 0 ;;
  -*) echo "error: unknown option $1 (usage: bash data_scripts/download_tum.sh [DEST])" >&2; exit 2 ;;
esac
DEST="${1:-${TSSLAM_DATA:-$HOME/datasets/tsslam_ref}/TUM}"
mkdir -p "$DEST"
for seq in freiburg1/rgbd_dataset_freiburg1_desk freiburg2/rgbd_dataset_freiburg2_xyz \
           freiburg3/rgbd_dataset_freiburg3_long_office_household; do
  name="$(basename "$seq")"
  if [ -f "$DEST/$name/rgb.txt" ] && [ ! -e "$DEST/$name.tgz" ]; then echo "have $name"; continue; fi
  fetched=no
  for host in https://cvg.cit.tum.de/rgbd/dataset https://vision.in.tum.de/rgbd/dataset; do
    if fetch "$host/$seq.tgz" "$DEST/$name.tgz"; then fetched=yes; break; fi
  done
  if [ "$fetched" != yes ]; then echo "error: could not download $seq.tgz from either host" >&2; exit 1; fi
  if ! gzip -t "$DEST/$name.tgz"; then echo "error: $DEST/$name.tgz is damaged; run the script again" >&2; exit 1; fi
  rm -rf "$DEST/$name.unpack"
  mkdir "$DEST/$name.unpack"
  tar -xzf "$DEST/$name.tgz" -C "$DEST/$name.unpack"
  if [ ! -f "$DEST/$name.unpack/$name/rgb.txt" ]; then
    echo "error: $DEST/$name.tgz holds no $name/rgb.txt" >&2; exit 1
  fi
  rm -rf "${DEST:?}/$name"
  mv "$DEST/$name.unpack/$name" "$DEST/$name"
  rm -rf "$DEST/$name.unpack" "$DEST/$name.tgz"
  echo "wrote $DEST/$name"
done
