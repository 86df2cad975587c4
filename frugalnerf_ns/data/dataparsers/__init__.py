"""Dataparsers for the layouts FrugalNeRF is evaluated on, all with the same few-shot view selection
(``common``): LLFF (``llff``), DTU (``dtu``), NeRF-synthetic (``blender``), RealEstate-10K (``realestate``),
nerfstudio-format and COLMAP scenes (``nerfstudio_format``), captures written in NeRF-synthetic's file names
(``transforms_capture``), a folder of photos without cameras (``photos``), and the default that detects the
layout (``auto``); ``registry`` registers them as ``ns-train`` subcommands.
"""
