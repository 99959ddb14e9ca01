"""The Gear-NeRF model (Sec 4.4 sampling, Eq 1-2 and 8-9 rendering and losses)."""
