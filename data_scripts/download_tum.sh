#!/usr/bin/env bash
# Download TUM RGB-D sequences used by Co-SLAM / TS-SLAM (not run in CI).
#   fr1/desk, fr2/xyz, fr3/long_office_household  (Sturm et al., IROS 2012; CC BY 4.0)
# Usage: bash data_scripts/download_tum.sh [DEST]   (default ${TSSLAM_DATA:-$HOME/datasets/tsslam_ref}/TUM)
# Each sequence lands in DEST/rgbd_dataset_freiburgN_NAME/ with rgb.txt, depth.txt, groundtruth.txt:
# the layout `tsslam_ref.data.load_sequence` reads; the camera (fr1/fr2/fr3) comes from the folder name.
# URLs: the TUM download server (verify before use; the older host vision.in.tum.de is tried second).
set -euo pipefail
DEST="${1:-${TSSLAM_DATA:-$HOME/datasets/tsslam_ref}/TUM}"
mkdir -p "$DEST"
for seq in freiburg1/rgbd_dataset_freiburg1_desk freiburg2/rgbd_dataset_freiburg2_xyz \
           freiburg3/rgbd_dataset_freiburg3_long_office_household; do
  name="$(basename "$seq")"
  if [ -f "$DEST/$name/rgb.txt" ]; then echo "have $name"; continue; fi
  for host in https://cvg.cit.tum.de/rgbd/dataset https://vision.in.tum.de/rgbd/dataset; do
    if curl -fL --retry 3 -o "$DEST/$name.tgz.part" "$host/$seq.tgz"; then break; fi
  done
  mv "$DEST/$name.tgz.part" "$DEST/$name.tgz"
  tar -xzf "$DEST/$name.tgz" -C "$DEST" && rm "$DEST/$name.tgz"
  echo "wrote $DEST/$name"
done
