"""Dataparsers for the three multi-view video datasets (installed as gear_nerfstudio.data_parsers).

Registered with nerfstudio through the `nerfstudio.dataparser_configs` entry point. Importing this
module must stay cheap and safe: nerfstudio imports every plugin when any command starts.
"""

from nerfstudio.plugins.registry_dataparser import DataParserSpecification

from gear_nerfstudio.data_parsers.google_immersive import GoogleImmersiveDataParserConfig
from gear_nerfstudio.data_parsers.neural_3d_video import Neural3DVideoDataParserConfig
from gear_nerfstudio.data_parsers.technicolor import TechnicolorDataParserConfig

technicolor_data = DataParserSpecification(
    config=TechnicolorDataParserConfig(),
    description="Technicolor light-field video: <Scene>_undist_<frame>_<cam>.png + cameras_parameters.txt",
)
neural_3d_video_data = DataParserSpecification(
    config=Neural3DVideoDataParserConfig(),
    description="Neural 3D Video (DyNeRF): camXX.mp4 + poses_bounds.npy",
)
google_immersive_data = DataParserSpecification(
    config=GoogleImmersiveDataParserConfig(),
    description="Google Immersive (DeepView) fisheye video: camera_XXXX.mp4 + models.json",
)
