"""Gear-NeRF for nerfstudio (Liu et al., CVPR 2024)."""
