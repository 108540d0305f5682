"""Entry point of the validating D-NeRF dataparser."""

from nerfstudio.plugins.registry_dataparser import DataParserSpecification

from garo_ns import compat
from garo_ns.data.dnerf import GaroDNeRFDataParserConfig

compat.install()

garo_dnerf_data = DataParserSpecification(
    config=GaroDNeRFDataParserConfig(),
    description="D-NeRF layout, validated up front; passes background and camera extent to the model.",
)
