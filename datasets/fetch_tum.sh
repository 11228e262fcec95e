#!/usr/bin/env bash
# Fetch and unpack one TUM RGB-D sequence: datasets/fetch_tum.sh rgbd_dataset_freiburg1_xyz [DEST]
set -euo pipefail
name="${1:?usage: fetch_tum.sh SEQUENCE_NAME [DEST]}"
dest="${2:-data}"
case "$name" in
  *freiburg1*) cam=freiburg1 ;; *freiburg2*) cam=freiburg2 ;; *freiburg3*) cam=freiburg3 ;;
  *) echo "cannot tell the camera (freiburg1/2/3) from $name" >&2; exit 2 ;;
esac
mkdir -p "$dest"
url="https://cvg.cit.tum.de/rgbd/dataset/$cam/$name.tgz"
echo "downloading $url"
curl -fL "$url" | tar -xz -C "$dest"
echo "unpacked into $dest/$name (run: slam run $dest/$name --out runs/$name)"
