"""Method presets registered with nerfstudio (installed as gear_nerfstudio.method_configs)."""
