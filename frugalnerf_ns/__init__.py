"""FrugalNeRF as a nerfstudio plugin (``ns-train frugalnerf``)."""

from frugalnerf_ns.checkpoint_compat import allow_nerfstudio_checkpoints
from frugalnerf_ns.ffmpeg_path import ensure_ffmpeg_on_path

# Importing the plugin (ns-train discovers it; ns-eval / ns-render / ns-viewer import it while reading
# config.yml) is what makes the checkpoints loadable again, and gives ns-render an ffmpeg.
allow_nerfstudio_checkpoints()
ensure_ffmpeg_on_path()

__version__ = "0.1.0"
