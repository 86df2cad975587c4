"""FrugalNeRF as a nerfstudio plugin (``ns-train frugalnerf``)."""

from frugalnerf_ns.checkpoint_compat import allow_nerfstudio_checkpoints

# Importing the plugin (ns-train discovers it; ns-eval / ns-render / ns-viewer import it while reading
# config.yml) is what makes the checkpoints loadable again.
allow_nerfstudio_checkpoints()

__version__ = "0.1.0"
