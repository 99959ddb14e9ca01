"""Errors about the input data."""

from gear_nerfstudio.errors import InputError


class DatasetError(InputError):
    """Bad input data; the message names the file and what is wrong with it."""
