"""Tools around the method: the demo and the synthetic scenes with ground truth."""
