"""DataParserSpecifications for the ``nerfstudio.dataparser_configs`` entry points (CLI subcommands)."""

from nerfstudio.plugins.registry_dataparser import DataParserSpecification

from frugalnerf_ns.data.dataparsers.auto import AutoDataParserConfig
from frugalnerf_ns.data.dataparsers.blender import BlenderDataParserConfig
from frugalnerf_ns.data.dataparsers.dtu import DTUDataParserConfig
from frugalnerf_ns.data.dataparsers.llff import LLFFDataParserConfig
from frugalnerf_ns.data.dataparsers.nerfstudio_format import (
    FewShotColmapDataParserConfig,
    FewShotNerfstudioDataParserConfig,
)
from frugalnerf_ns.data.dataparsers.photos import PhotosDataParserConfig
from frugalnerf_ns.data.dataparsers.realestate import RealEstateDataParserConfig

frugal_auto = DataParserSpecification(AutoDataParserConfig(), "detect the layout of --data (FrugalNeRF default)")
frugal_llff = DataParserSpecification(LLFFDataParserConfig(), "LLFF: poses_bounds.npy + images_N/, NDC")
frugal_dtu = DataParserSpecification(DTUDataParserConfig(), "DTU / IDR / NeuS: cameras_sphere.npz, image/ or images/, mask/")
frugal_blender = DataParserSpecification(
    BlenderDataParserConfig(), "transforms_train.json / transforms_test.json: NeRF-synthetic (RGBA), or a real capture in those names"
)
frugal_realestate = DataParserSpecification(
    RealEstateDataParserConfig(), "RealEstate-10K (ViP-NeRF layout): rgb/, CameraIntrinsics.csv, CameraExtrinsics.csv"
)
frugal_nerfstudio = DataParserSpecification(FewShotNerfstudioDataParserConfig(), "nerfstudio transforms.json, checked")
frugal_colmap = DataParserSpecification(FewShotColmapDataParserConfig(), "COLMAP (images/ + sparse/0)")
frugal_photos = DataParserSpecification(
    PhotosDataParserConfig(), "a folder of 2-4 photos without cameras: cameras estimated with pycolmap, cached"
)
