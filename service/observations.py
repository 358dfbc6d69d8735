"""Observations as clients send them (nested lists, raw tensors, base64) turned into NumPy arrays."""

from __future__ import annotations

import base64
import binascii
import math
from collections.abc import Sequence

import numpy as np

from gmt.service.errors import InvalidArgument

DTYPES = (
    "bool",
    "uint8",
    "int8",
    "uint16",
    "int16",
    "uint32",
    "int32",
    "uint64",
    "int64",
    "float16",
    "float32",
    "float64",
)
MAX_ABS_VALUE = 1e9  # largest |value| of an observation (and target): far beyond any physical quantity, far
# below where the shipped model's forward pass overflows (about 1e19), and a bound the OpenAPI schema states exactly
MAX_DIMS = 8


def decode_base64(data: str) -> bytes:
    """Standard base64 (with padding) to bytes.

    Raises:
        InvalidArgument: `data` is not valid base64.
    """
    try:
        return base64.b64decode(data, validate=True)
    except (binascii.Error, ValueError) as e:
        raise InvalidArgument(f"observation.data is not valid base64: {e}") from None


def decode_tensor(data: bytes, dtype: str, shape: Sequence[int]) -> np.ndarray:
    """A raw little-endian array.

    Raises:
        InvalidArgument: unsupported dtype, negative dimension, or a byte count that does not fill the shape.
    """
    if dtype not in DTYPES:
        raise InvalidArgument(f"observation dtype {dtype!r} is not supported; use one of {', '.join(DTYPES)}")
    dims = [int(s) for s in shape]
    if len(dims) > MAX_DIMS:
        raise InvalidArgument(
            f"observation shape has {len(dims)} dimensions; at most {MAX_DIMS} are accepted"
        )
    if any(s < 0 for s in dims):
        raise InvalidArgument(f"observation shape {dims} has a negative dimension")
    dt = np.dtype(dtype).newbyteorder("<")
    need = math.prod(dims) * dt.itemsize  # Python ints: a huge shape cannot overflow into a small number
    if need != len(data):
        raise InvalidArgument(f"observation data has {len(data)} bytes; shape {dims} of {dtype} needs {need}")
    try:
        return np.frombuffer(data, dtype=dt).reshape(dims)
    except (ValueError, OverflowError):  # an empty array with a huge dimension, e.g. [0, 2**62]
        raise InvalidArgument(f"observation shape {dims} is too large") from None


def to_array(obs: object) -> np.ndarray:
    """A nested list (or array) as an array; rejects ragged lists and finite values beyond +-MAX_ABS_VALUE.

    Size, dtype kind and NaN/Inf are checked afterwards by the model's `prepare_observation`.

    Raises:
        InvalidArgument: ragged nesting, or a finite value whose magnitude exceeds MAX_ABS_VALUE.
    """
    if isinstance(obs, np.ndarray):
        x = obs
    else:
        try:
            x = np.asarray(obs)
        except (ValueError, TypeError, OverflowError) as e:
            raise InvalidArgument(f"observation is not a rectangular numeric array: {e}") from None
    if x.dtype == object and x.size:  # integers past int64 (anything else is refused as non-numeric later)
        for i, v in enumerate(x.ravel()):
            if type(v) is int and abs(v) > MAX_ABS_VALUE:
                raise InvalidArgument(f"observation value at index {i} is outside [-1e9, 1e9]")
    if x.size and (x.dtype.kind == "f" or (x.dtype.kind in "iu" and x.dtype.itemsize > 2)):
        if x.dtype.kind == "f" and np.abs(x).max() <= MAX_ABS_VALUE:  # fast path (False for NaN and Inf)
            return x
        v = x if x.dtype.kind == "f" else x.astype(np.float64)
        with np.errstate(invalid="ignore"):
            big = np.abs(v) > MAX_ABS_VALUE  # False for NaN; Inf is reported as non-finite later
        big &= np.isfinite(v)
        if big.any():
            i = int(np.flatnonzero(big.ravel())[0])
            raise InvalidArgument(f"observation value at index {i} is outside [-1e9, 1e9]")
    return x
