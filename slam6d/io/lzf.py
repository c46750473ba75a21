"""LZF decompression (the codec of PCL's ``binary_compressed`` PCD bodies), compiled with numba.

A byte-by-byte decoder in pure Python would take seconds per scan; compiled and cached it is as
fast as the C original.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def decompress(src: np.ndarray, dst: np.ndarray) -> int:
    """Decode ``src`` into ``dst``; returns the bytes written, or -1 if the stream is corrupt."""
    ip = 0
    op = 0
    n_in = src.shape[0]
    n_out = dst.shape[0]
    while ip < n_in:
        ctrl = int(src[ip])
        ip += 1
        if ctrl < 32:  # literal run of ctrl + 1 bytes
            run = ctrl + 1
            if op + run > n_out or ip + run > n_in:
                return -1
            for k in range(run):
                dst[op + k] = src[ip + k]
            op += run
            ip += run
        else:  # back-reference: length in the top 3 bits (7 = extended), distance in the rest
            length = ctrl >> 5
            if ip >= n_in:
                return -1
            if length == 7:
                length += int(src[ip])
                ip += 1
                if ip >= n_in:
                    return -1
            ref = op - ((ctrl & 0x1F) << 8) - 1 - int(src[ip])
            ip += 1
            length += 2
            if ref < 0 or op + length > n_out:
                return -1
            for k in range(length):  # may overlap its own output: copy forwards, byte by byte
                dst[op + k] = dst[ref + k]
            op += length
    return op
