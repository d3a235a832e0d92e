"""Rows of a chunked Zarr array, with a chunk whose bytes do not decode named in the error.

Zarr reports a chunk overwritten with garbage as the codec's own error (zstd's `RuntimeError: Zstd decompression
error`, or a `ValueError` when the bytes decode to the wrong size), which names neither the store nor the chunk.
`read_rows` turns it into a `CorruptChunkError` (a ValueError: a stage ends with one line and status 2) naming
where the array is, the chunk's key and the rows it holds.
"""

from __future__ import annotations

import numpy as np
import zarr

CODEC_ERRORS = (RuntimeError, ValueError)  # what a codec raises on bytes it cannot decode


class CorruptChunkError(ValueError):
    """A chunk of a store's array whose bytes do not decode."""


def _bad_chunk(array: zarr.Array, start: int, stop: int) -> tuple[int, str, BaseException] | None:
    """(index along axis 0, chunk key, the codec's error) of the first chunk of rows [start, stop) that does not
    decode; None if each decodes on its own."""
    rows = array.chunks[0]
    for i in range(start // rows, -(-stop // rows)):
        try:
            array[i * rows:(i + 1) * rows]
        except CODEC_ERRORS as err:
            return i, array.metadata.encode_chunk_key((i,) + (0,) * (array.ndim - 1)), err
    return None


def read_rows(array: zarr.Array, start: int, stop: int, where: str, rows_name: str = "rows") -> np.ndarray:
    """`array[start:stop]` along axis 0. A chunk that does not decode raises CorruptChunkError: '`where`: chunk
    <key> (<rows_name> a-b) does not decode (<codec error>)'; `where` names the store, episode and array."""
    try:
        return np.asarray(array[start:stop])
    except CODEC_ERRORS as err:
        found = _bad_chunk(array, start, stop)
        if found is None:  # only the window as a whole fails: name its chunks
            rows = array.chunks[0]
            first, last = start // rows, (stop - 1) // rows
            raise CorruptChunkError(f"{where}: chunks {first}-{last} ({rows_name} {start}-{stop - 1}) do not decode "
                                    f"({type(err).__name__}: {err})") from err
        i, key, cause = found
        rows = array.chunks[0]
        last_row = min((i + 1) * rows, array.shape[0]) - 1
        raise CorruptChunkError(f"{where}: chunk {key} ({rows_name} {i * rows}-{last_row}) does not decode "
                                f"({type(cause).__name__}: {cause})") from err
