"""FrugalNeRF as a nerfstudio plugin (``ns-train frugalnerf``).

The package is a house of rooms, each importing only from its own floor or the floors below
(``tests/test_layers.py`` fails on an upward import):

5. ``bench/``    ``frugalnerf-bench``: the development measurements, one pipeline builder, one table writer
4. ``run/``      presets, option checks, pipeline, trainer, checkpoints
3. ``tools/``    offline evaluator, demo, video, sweep runner and quality gate
2. ``model/``    model and its config, rendering, objective, losses, geometric adaptation; beside it, importing
   nothing of it, ``data/``: dataparsers, dataset, datamanager, sparse and monocular depth, splits, procedural scene
1. ``geometry/`` rays, NDC, reprojection, camera conventions, novel-view and video poses, scene analysis;
   ``field/`` tensorial grids, radiance field, colour MLP; ``scoring/`` image metrics and offline LPIPS
0. this folder: one-line errors (``errors``), progress lines (``progress``), keyed caches beside the data
   (``cache``), the config tables and where files are (``config_files``), old module names (``legacy_names``),
   the typed batches the datamanager hands the model (``batch``), and the start-up hooks run below: nerfstudio's
   checkpoints loadable under torch >= 2.6 (``checkpoint_compat``) and an ffmpeg for ``ns-render`` (``ffmpeg_path``)
"""

from frugalnerf_ns import legacy_names

# Before anything else: a config.yml written before the rooms names the old flat modules.
legacy_names.install()

from frugalnerf_ns.checkpoint_compat import allow_nerfstudio_checkpoints  # noqa: E402
from frugalnerf_ns.ffmpeg_path import provide_ffmpeg_for_video_commands  # noqa: E402

# Importing the plugin (ns-train discovers it; ns-eval / ns-render / ns-viewer import it while reading
# config.yml) is what makes the checkpoints loadable again; in ns-render it also gives nerfstudio an ffmpeg
# when the machine has none (ffmpeg_path.py: appended to PATH from a private folder, never a shared one).
allow_nerfstudio_checkpoints()
provide_ffmpeg_for_video_commands()

__version__ = "0.1.0"
