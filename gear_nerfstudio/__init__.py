"""Gear-NeRF for nerfstudio (Liu et al., CVPR 2024)."""

from gear_nerfstudio.dependency_warnings import silence_dependency_warnings
from gear_nerfstudio.errors import report_input_errors

report_input_errors()
silence_dependency_warnings()
