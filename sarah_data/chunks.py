"""Shard chunks encoded here and written with HDF5's direct chunk write.

Every per-frame dataset of a shard is declared with the filter pipeline shuffle + deflate (gzip)
+ fletcher32, so any HDF5 build reads it with its built-in filters. Writing through that pipeline
(level 4) costs ~15 ms of CPU per dyad-second, more than everything else prep does, mostly zlib
searching a float32's low-order byte planes for matches that are rare or absent: after shuffle,
bytes 0 and 1 (mantissa noise) deflate to ~0.93 of their size, byte 2 (exponent bit, top of the
mantissa) to ~0.70, byte 3 (sign, exponent) to ~0.05. This module produces the same three
filters' output itself and chooses inside the deflate format:

    shuffle      byte planes, as H5Z_filter_shuffle lays them out
    deflate      one zlib stream: a float's low-order planes (STORED_FLOAT_PLANES of them) as
                 *stored* deflate blocks (a copy), the rest deflated at level 1; an adler32
    fletcher32   HDF5's checksum of the encoded bytes, appended little-endian

The stream is plain zlib: HDF5's inflate reads it like any other (and copies stored blocks, so
reading is faster too). Output depends only on the data and the zlib version. On the fixture
corpus of sarah-bench, CPU per dyad-second and shard size against the uncompressed arrays:

    HDF5's pipeline, level 4          ~15 ms   0.60
    2 planes stored, level 1           4.5 ms  0.67
    3 planes stored, level 1 (this)    1.6 ms  0.74
"""

from __future__ import annotations

import zlib

import h5py
import numpy as np

# Of the deflated planes, and the level the datasets' filter pipeline declares. Level 4 costs
# ~25 % more CPU here for files ~2 % smaller.
LEVEL = 1
# A float's low-order byte planes stored rather than deflated (of 4 for float32). 3 keeps prep
# above 100x real time on two cores; 2 makes shards ~10 % smaller for 3x the compression CPU.
STORED_FLOAT_PLANES = 3
_ZLIB_HEADER = bytes((0x78, 0x01))  # deflate, 32 KiB window, "fastest" level class (level 1)
_STORED_MAX = 0xFFFF  # bytes per stored deflate block


def stored_planes(dtype: np.dtype) -> int:
    """Low-order byte planes stored rather than deflated: of a float, all but the top one (at
    most STORED_FLOAT_PLANES); of anything else, none."""
    dtype = np.dtype(dtype)
    return min(STORED_FLOAT_PLANES, dtype.itemsize - 1) if dtype.kind == "f" else 0


def shuffle(block: np.ndarray) -> bytes:
    """H5Z_filter_shuffle: byte k of every element, for k = 0 .. itemsize-1 (memory order)."""
    size = block.dtype.itemsize
    raw = np.ascontiguousarray(block).view(np.uint8)
    return raw.tobytes() if size == 1 else raw.reshape(-1, size).T.tobytes()


def deflate(data: bytes, stored: list[tuple[int, int]]) -> bytes:
    """A zlib stream of `data`: the (start, stop) byte ranges in `stored` (sorted, disjoint, not
    reaching the end) as stored blocks, everything between them deflated."""
    view = memoryview(data)
    parts, position = [_ZLIB_HEADER], 0
    for start, stop in stored + [(len(data), len(data))]:
        if start > position:
            # A fresh deflater starts on a byte boundary and refers to nothing before it; a sync
            # flush ends it on one, a finish (at the end of the data) makes its block the last.
            compressor = zlib.compressobj(LEVEL, zlib.DEFLATED, -15)
            parts += [compressor.compress(view[position:start]),
                      compressor.flush(zlib.Z_FINISH if start == len(data) else zlib.Z_SYNC_FLUSH)]
        for piece_start in range(start, stop, _STORED_MAX):
            piece = view[piece_start:min(piece_start + _STORED_MAX, stop)]
            # BFINAL=0, BTYPE=00 (stored), padded to the byte; then LEN and its complement NLEN
            parts.append(b"\x00" + len(piece).to_bytes(2, "little")
                         + (len(piece) ^ 0xFFFF).to_bytes(2, "little"))
            parts.append(piece)
        position = max(position, stop)
    parts.append(zlib.adler32(data).to_bytes(4, "big"))
    return b"".join(parts)


def fletcher32(data: bytes) -> int:
    """HDF5's H5_checksum_fletcher32, in closed form.

    The C loop sums big-endian 16-bit words (an odd last byte is the high byte of one more word):
    sum1 = sum(w), sum2 = sum((n - i) * w[i]), folded mod 65535 with end-around carries. Folding
    keeps each sum congruent mod 65535 and never yields 0 from a positive sum, so the result is
    0 for an all-zero input and otherwise the residue in 1..65535.
    """
    if len(data) % 2:
        data = data + b"\x00"
    n = len(data) // 2
    # sum(i * w[i]) with i = 256 * row + column, from row and column sums of a (rows, 256) view
    words = np.frombuffer(data + b"\x00" * (-len(data) % 512), ">u2").reshape(-1, 256)
    rows, columns = words.sum(axis=1, dtype=np.int64), words.sum(axis=0, dtype=np.int64)
    sum1 = int(rows.sum())
    weighted = (256 * int(np.dot(np.arange(len(rows), dtype=np.int64), rows))
                + int(np.dot(np.arange(256, dtype=np.int64), columns)))
    sum2 = n * sum1 - weighted

    def fold(total: int) -> int:
        return 0 if total == 0 else (total - 1) % 0xFFFF + 1

    return (fold(sum2) << 16) | fold(sum1)


def encode_chunk(block: np.ndarray, rows: int | None = None) -> bytes:
    """One full chunk through shuffle, deflate and fletcher32, as HDF5 stores it.

    Only the first `rows` rows (default: all) are data; the rest is zero padding, which is
    deflated (to almost nothing) rather than stored.
    """
    shuffled = shuffle(block)
    per_plane = block.size
    used = per_plane if rows is None else per_plane // block.shape[0] * rows
    stored = [(k * per_plane, k * per_plane + used) for k in range(stored_planes(block.dtype))]
    encoded = deflate(shuffled, _merged(stored))
    return encoded + fletcher32(encoded).to_bytes(4, "little")


def _merged(ranges: list[tuple[int, int]]) -> list[tuple[int, int]]:
    merged: list[tuple[int, int]] = []
    for start, stop in ranges:
        if merged and merged[-1][1] == start:
            merged[-1] = (merged[-1][0], stop)
        else:
            merged.append((start, stop))
    return merged


def write_chunks(dataset: h5py.Dataset, data: np.ndarray) -> None:
    """Fill a chunked (time-axis) dataset whose pipeline is shuffle + gzip + fletcher32.

    The last chunk is padded with zeros (the fill value) to the full chunk shape, as HDF5 stores
    partial edge chunks.
    """
    rows = dataset.chunks[0]
    tail = (0,) * (data.ndim - 1)
    for start in range(0, data.shape[0], rows):
        block = data[start:start + rows]
        used = block.shape[0]
        if used < rows:
            block = np.concatenate([block, np.zeros((rows - used,) + data.shape[1:], data.dtype)])
        dataset.id.write_direct_chunk((start,) + tail, encode_chunk(block, used))
