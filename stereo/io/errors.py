"""Exceptions raised by the file readers and writers of `stereo.io`."""

from __future__ import annotations


class StereoIOError(ValueError):
    """Base class: a file or array could not be read or written in the expected format."""


class MalformedFileError(StereoIOError):
    """A file exists but its content is not what its format requires (message names file and fault)."""


class ArrayFormatError(StereoIOError):
    """An array handed to a writer has a shape, dtype or value range the format cannot store."""
