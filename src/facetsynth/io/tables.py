"""Per-point (P, T, F) tables kept on their support: the slices and partial NDFs between stages.

A point's partial NDF is defined only where W > 0 (paper 002 eq. 12), a third of
the cells of the direction grid on the paper-scale rig, and its resampled slice is
read only next to the light directions its lights covered (about half). Stored
densely, the two were 85 % of the intermediate data at 800 x 800 points
(docs/decisions.md, "Disk at the paper's scale"). A support table is a folder:

- ``table.json``: the shape (P, T, F) and the channels' names;
- ``mask.npy``: (P, ceil(T F / 8)) uint8, each point's support as bits
  (``numpy.packbits`` of its cells in row-major order);
- ``offsets.npy``: (P + 1,) int64, where each point's values start;
- ``CHANNEL.npy``: (nnz,) half floats (:func:`facetsynth.io.half.as_half`), the
  values on the support, point after point, cells in row-major order; several
  channels share one support (the partial NDF's D and W).

Every file is a memory-mappable .npy; rows read through :meth:`SupportTable.rows`
come back dense, 0 off the support. Written streaming, a block of points at a
time, and published whole (:func:`facetsynth.io.fileio.atomic_dir`).
"""

from __future__ import annotations

import contextlib
import math
from pathlib import Path
from typing import Callable, Iterator

import numba
import numpy as np

from .fileio import PathLike, atomic_dir, npy_writer, read_json, read_npy, write_json, write_npy
from .half import HALF, HALF_VALUES, as_half

TABLE_FILE = "table.json"


class SupportTable:
    """A support table folder, read by rows (each read maps its files and unmaps them after, as
    :class:`facetsynth.io.fileio.NpyRows` does)."""

    def __init__(self, folder: PathLike):
        self.folder = Path(folder)
        meta = read_json(self.folder / TABLE_FILE)
        self.shape = tuple(int(v) for v in meta["shape"])
        self.channels = tuple(meta["channels"])
        self.offsets = read_npy(self.folder / "offsets.npy")
        self.cells = math.prod(self.shape[1:])
        if self.offsets.shape != (self.shape[0] + 1,):
            raise ValueError(f"{self.folder}: offsets.npy holds {self.offsets.shape} entries for "
                             f"{self.shape[0]} points")

    def __len__(self) -> int:
        return self.shape[0]

    def rows(self, channel: str) -> "SupportRows":
        """The dense rows of one channel: ``rows[index]`` (any numpy index on the points)."""
        if channel not in self.channels:
            raise KeyError(f"{self.folder}: no channel {channel!r} (it holds {', '.join(self.channels)})")
        return SupportRows(self, channel)

    def support(self, index) -> np.ndarray:
        """Which cells of the points ``index`` are stored: bool (n, T, F) (or (T, F) for one point)."""
        rows, scalar = _point_indices(index, len(self))
        bits = self._bits(rows).reshape((len(rows),) + self.shape[1:])
        return bits[0] if scalar else bits

    def _bits(self, rows: np.ndarray) -> np.ndarray:
        """The support of the points ``rows`` (point numbers), bool (n, T F)."""
        return np.unpackbits(self._packed(rows), axis=1, count=self.cells).astype(bool)

    def _packed(self, rows: np.ndarray) -> np.ndarray:
        """The packed support (``mask.npy``'s rows) of the points ``rows``, read in one stretch for a run."""
        mask = np.load(self.folder / "mask.npy", mmap_mode="r")
        packed = np.array(mask[_as_run(rows) or rows])
        del mask
        return packed

    def _dense(self, channel: str, index, support: np.ndarray | None = None) -> np.ndarray:
        """Dense rows of ``channel``; ``support``: the points' support when the caller has read it already."""
        rows, scalar = _point_indices(index, len(self))
        support = self._bits(rows) if support is None else support.reshape(len(rows), self.cells)
        values = np.load(self.folder / f"{channel}.npy", mmap_mode="r")
        out = np.zeros((len(rows), self.cells), values.dtype)
        run = _as_run(rows)
        if run is not None:        # a block of consecutive points: one read
            out[support] = values[self.offsets[run.start]:self.offsets[run.stop]]
        else:
            for k, r in enumerate(rows):
                out[k, support[k]] = values[self.offsets[r]:self.offsets[r + 1]]
        del values
        out = out.reshape((len(rows),) + self.shape[1:])
        return out[0] if scalar else out

    def sector_sums(self, channel: str, index, sectors: int) -> np.ndarray:
        """Sums (n, T, ``sectors``) in float64 of ``channel`` over each ring's runs of F / ``sectors`` cells, at the
        points ``index`` (an integer array), read straight from the stored support: bitwise
        ``rows(channel)[index].reshape(n, T, sectors, -1).sum(axis=-1, dtype=float)`` (cells off the support add
        nothing there either), without making the dense rows (the partial NDFs' coarse grid in cluster: 2 x
        numpy's sum, and no half-float rows)."""
        n_theta, n_phi = self.shape[1], math.prod(self.shape[2:])
        if n_phi % sectors:
            raise ValueError(f"{self.folder}: {n_phi} cells a ring do not split into {sectors} sectors")
        rows = np.asarray(index, np.intp)
        values = np.load(self.folder / f"{channel}.npy", mmap_mode="r")
        sums = _support_sector_sums(self._packed(rows), np.asarray(values).view(np.uint16), self.offsets[rows],
                                    HALF_VALUES, n_theta, n_phi, sectors)
        del values
        return sums


@numba.njit(cache=True, nogil=True)
def _support_sector_sums(bits: np.ndarray, values: np.ndarray, starts: np.ndarray, half_values: np.ndarray,
                         n_theta: int, n_phi: int, sectors: int) -> np.ndarray:
    """:meth:`SupportTable.sector_sums` of rows whose packed support is ``bits`` (n, bytes) and whose values (half
    float bits, read through ``half_values``) start at ``starts`` (n,) in ``values``: each sum in cell order, from
    0.0, as numpy's sum of a short row."""
    m = n_phi // sectors
    out = np.zeros((bits.shape[0], n_theta, sectors))
    for a in range(bits.shape[0]):
        at = starts[a]
        for t in range(n_theta):
            for j in range(sectors):
                total = 0.0
                for c in range(t * n_phi + j * m, t * n_phi + (j + 1) * m):
                    if (bits[a, c >> 3] >> (7 - (c & 7))) & 1:
                        total += half_values[values[at]]
                        at += 1
                out[a, t, j] = total
    return out


class SupportRows:
    """One channel of a :class:`SupportTable` as a (P, T, F) tensor read by rows (``shape``, ``dtype``,
    ``len``, ``rows[index]``): what :class:`facetsynth.io.fileio.NpyRows` is for a dense .npy."""

    def __init__(self, table: SupportTable, channel: str):
        self.table, self.channel = table, channel
        self.shape, self.dtype = table.shape, np.dtype(HALF)

    def __len__(self) -> int:
        return self.shape[0]

    def __getitem__(self, index) -> np.ndarray:
        return self.table._dense(self.channel, index)

    def sector_sums(self, index, sectors: int) -> np.ndarray:
        """:meth:`SupportTable.sector_sums` of this channel."""
        return self.table.sector_sums(self.channel, index, sectors)


@contextlib.contextmanager
def support_writer(folder: PathLike, shape: tuple[int, ...],
                   channels: tuple[str, ...] = ("values",)) -> Iterator[Callable[..., None]]:
    """Write a support table of ``shape`` (P, T, F) atomically, blocks of points in order: yields
    ``write(support, **values)``, ``support`` bool (n, T, F) and one (n, T, F) array per channel (their
    values off the support are dropped). Raises ValueError when the blocks do not fill ``shape``."""
    shape = tuple(int(v) for v in shape)
    cells = math.prod(shape[1:])
    offsets = [np.zeros(1, np.int64)]
    header = {"descr": np.lib.format.dtype_to_descr(np.dtype(HALF)), "fortran_order": False}
    with atomic_dir(folder) as staging, contextlib.ExitStack() as files:
        write_mask = files.enter_context(npy_writer(staging / "mask.npy", np.uint8, (shape[0], (cells + 7) // 8)))
        out = {c: files.enter_context(open(staging / f"{c}.npy", "wb")) for c in channels}
        for f in out.values():   # the header is rewritten with the final length: numpy pads it for that
            np.lib.format.write_array_header_1_0(f, {**header, "shape": (0,)})
        written = 0

        def write(support: np.ndarray, **values: np.ndarray) -> None:
            nonlocal written
            support = np.asarray(support, bool)
            n = len(support)
            if support.shape[1:] != shape[1:] or written + n > shape[0] or set(values) != set(channels):
                raise ValueError(f"{folder}: a block of shape {support.shape} with channels {sorted(values)} does "
                                 f"not fit the table {shape} of {list(channels)} after {written} rows")
            flat = support.reshape(n, cells)
            write_mask(np.packbits(flat, axis=1))
            for c, f in out.items():
                f.write(as_half(np.asarray(values[c]).reshape(n, cells)[flat]).tobytes())
            offsets.append(offsets[-1][-1] + np.cumsum(flat.sum(axis=1), dtype=np.int64))
            written += n

        yield write
        if written != shape[0]:
            raise ValueError(f"{folder}: {written} rows written of {shape[0]}")
        ends = np.concatenate(offsets)
        for f in out.values():
            f.seek(0)
            np.lib.format.write_array_header_1_0(f, {**header, "shape": (int(ends[-1]),)})
        files.close()
        write_npy(staging / "offsets.npy", ends)
        write_json(staging / TABLE_FILE, {"shape": list(shape), "channels": list(channels), "dtype": "float16",
                                          "stored_fraction": float(ends[-1]) / max(shape[0] * cells, 1)})


def join_tables(parts: list[PathLike], out: PathLike, n_points: int, block: int = 256) -> None:
    """Scatter parts' support tables, given in point order, streamed into one table of ``n_points``: the
    unsplit run's, bit for bit."""
    tables = [SupportTable(p) for p in parts]
    held = sum(len(t) for t in tables)
    if held != n_points:
        raise ValueError(f"{out}: the scatter parts hold {held} points, the capture {n_points}")
    with support_writer(out, (n_points,) + tables[0].shape[1:], tables[0].channels) as write:
        for t in tables:
            for start in range(0, len(t), block):
                rows = slice(start, min(start + block, len(t)))
                support = t.support(rows)            # read once for every channel
                write(support, **{c: t._dense(c, rows, support) for c in t.channels})


def _point_indices(index, n: int) -> tuple[np.ndarray, bool]:
    """``index`` (int, slice, integer or bool array) as point numbers, and whether it named one point. A
    slice or an int (the tile reads) costs nothing per point of the table."""
    if isinstance(index, slice):
        return np.arange(*index.indices(n)), False
    if isinstance(index, (int, np.integer)) and not isinstance(index, bool):
        return np.array([range(n)[index]]), True
    rows = np.arange(n)[index]
    return np.atleast_1d(rows), np.ndim(rows) == 0


def _as_run(rows: np.ndarray) -> slice | None:
    """``rows`` as a slice when they are consecutive and increasing (one contiguous read), else None."""
    if rows.size and rows[-1] - rows[0] == rows.size - 1 and (rows.size == 1 or np.all(np.diff(rows) == 1)):
        return slice(int(rows[0]), int(rows[-1]) + 1)
    return None


def load(folder: PathLike, channel: str = "values") -> np.ndarray:
    """A support table's channel as one dense (P, T, F) array (small tables, tests and inspection)."""
    return SupportTable(folder).rows(channel)[:]
