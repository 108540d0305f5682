"""Entry points of the plugin's dataparsers."""

from nerfstudio.plugins.registry_dataparser import DataParserSpecification

from garo_ns import compat
from garo_ns.data.dnerf import GaroDNeRFDataParserConfig
from garo_ns.data.nerfds import NerfDSDataParserConfig

compat.install()

garo_dnerf_data = DataParserSpecification(
    config=GaroDNeRFDataParserConfig(),
    description="D-NeRF layout, validated up front; passes background and camera extent to the model.",
)

nerfds_data = DataParserSpecification(
    config=NerfDSDataParserConfig(),
    description="Real monocular captures: NeRF-DS / HyperNeRF, or your own video processed by ns-process-data.",
)
