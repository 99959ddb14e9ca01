"""Synthetic dynamic scenes with ground truth, written in the three datasets' on-disk formats."""
