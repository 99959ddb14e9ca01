"""Data: the datamanager with SAM features, the on-disk frame cache, dataset errors."""
