"""Errors raised by the body package. Both are ValueErrors so callers can catch either."""


class ModelFileError(ValueError):
    """A model file is missing, unreadable, lacks a key or holds an array of the wrong shape."""


class ParameterError(ValueError):
    """Body-model parameters have the wrong shape or hold NaN/Inf."""
