"""FrugalNeRF as a nerfstudio plugin (``ns-train frugalnerf``)."""

from frugalnerf_ns.checkpoint_compat import allow_nerfstudio_checkpoints
from frugalnerf_ns.ffmpeg_path import provide_ffmpeg_for_video_commands

# Importing the plugin (ns-train discovers it; ns-eval / ns-render / ns-viewer import it while reading
# config.yml) is what makes the checkpoints loadable again; in ns-render it also gives nerfstudio an ffmpeg
# when the machine has none (ffmpeg_path.py: appended to PATH from a private folder, never a shared one).
allow_nerfstudio_checkpoints()
provide_ffmpeg_for_video_commands()

__version__ = "0.1.0"
