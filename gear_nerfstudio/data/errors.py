"""Errors about the input data."""


class DatasetError(ValueError):
    """Bad input data; the message names the file and what is wrong with it."""
