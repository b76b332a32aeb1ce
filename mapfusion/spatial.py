"""A cell index over the way-points for single radius queries (issue 21).

A k-d tree answers one ball query in 11–15 µs here (issue 21's machine), much of it spent building
a Python list of the hits. Here the points are bucketed in square cells, and stored band by band: band
r holds the points of the rows of cells r, r + 1 and r + 2, column by column. A disc no wider than a
cell in radius covers at most three rows and three columns of cells, which are one contiguous slice
of one band: a query is a few arithmetic steps, two table look-ups and a slice of an array that
already holds each point's position and heading, with no tree walk, no joining of pieces and no
per-hit Python object. Every point is stored three times. The k-d tree stays for the batch
matcher's k-nearest queries.
"""

from __future__ import annotations

import array
import math

import numpy as np

from .geometry import as_complex

#: Side of a cell (m): the matcher's default radius, so a query of that radius is one band's slice.
CELL_M = 20.0
#: The rows of cells a band holds (its own and the next two).
BAND_ROWS = 3
#: A table of every band's column starts is kept when it has at most this many entries per point
#: (and at least this many cells are allowed): a sparse regional map falls back to a binary search.
DENSE_CELLS_PER_POINT, DENSE_CELLS_MIN = 4, 1 << 20


class CellIndex:
    """Points (N, 2) in cells of ``cell_m``, stored in bands of three rows of cells (module docstring).

    Band by band and within a band column by column, then row by row, then by point index (3N entries
    at most), ``z`` holds the points' positions as complex numbers x + iy and ``block`` (3, ·) their
    headings' cosines and sines and a sign (the matcher's: -1 where both directions of travel are
    legal, +1 where only the heading's); ``rank`` maps each entry to its point's place in row-major
    cell order (the order :meth:`query` answers in) and ``by_cell`` that order to the point indices."""

    def __init__(self, xy_m: np.ndarray, cos: np.ndarray, sin: np.ndarray, sign: np.ndarray | None = None,
                 cell_m: float = CELL_M) -> None:
        xy = np.asarray(xy_m, dtype=float).reshape(-1, 2)
        self.cell_m = float(cell_m)
        n = len(xy)
        lo = xy.min(axis=0) if n else np.zeros(2)
        self.x0, self.y0 = float(lo[0]), float(lo[1])
        cx = np.floor((xy[:, 0] - self.x0) / self.cell_m).astype(np.int64)
        cy = np.floor((xy[:, 1] - self.y0) / self.cell_m).astype(np.int64)
        self.ncol = int(cx.max()) + 1 if n else 1
        self.nrow = int(cy.max()) + 1 if n else 1
        cell = cy * self.ncol + cx
        by_cell = np.argsort(cell, kind="stable")  # row-major cell order, then point index
        cell = cell[by_cell]
        sign = np.full(n, -1.0) if sign is None else np.asarray(sign, dtype=float)
        # (row by row into one array: numpy's 2-D fancy indexing is several times slower at this size)
        in_cells = _take_rows((np.asarray(cos, dtype=float), np.asarray(sin, dtype=float), sign), by_cell)
        z_in_cells = as_complex(xy).take(by_cell)
        # every non-empty cell (r, c) is part of bands r - 2, r - 1 and r: those (band, column, row) triples in
        # order, each standing for its cell's run of points in cell order
        first = np.flatnonzero(np.r_[True, cell[1:] != cell[:-1]]) if n else np.zeros(0, dtype=np.intp)
        size = np.diff(np.r_[first, n])
        row, col = np.divmod(cell[first], self.ncol)
        dr = np.repeat(np.arange(BAND_ROWS), len(first))
        band = np.tile(row, BAND_ROWS) - dr
        run = np.tile(np.arange(len(first)), BAND_ROWS)
        ok = band >= 0
        band, run, dr = band[ok], run[ok], dr[ok]
        key = band * self.ncol + col[run]
        order = np.argsort(key * BAND_ROWS + dr, kind="stable")
        key, run = key[order], run[order]
        counts = size[run]
        ends = np.cumsum(counts)
        #: each entry's place in row-major cell order (where :meth:`query` answers in that order)
        self.rank = np.repeat(first[run] - (ends - counts), counts) + np.arange(int(ends[-1]) if n else 0)
        self.by_cell = by_cell
        #: each entry's band × columns + column (for the binary search where no table is kept)
        self.key: np.ndarray | None = np.repeat(key, counts)
        # positions as complex numbers (one subtraction and one absolute value give the distances); cos, sin
        # and sign as the rows of one array: a query takes one slice of every row at once, and each quantity
        # stays contiguous for numpy's loops
        self.z = z_in_cells.take(self.rank)
        self.block = _take_rows(in_cells, self.rank)
        cells = self.ncol * self.nrow
        self._start: array.array | None = None  # (compact: a query's look-ups stay in few cache lines)
        if cells <= max(DENSE_CELLS_PER_POINT * n, DENSE_CELLS_MIN):
            self._start = array.array("q", np.searchsorted(self.key, np.arange(cells + 1)).astype(np.int64).tobytes())
            self.key = None  # (the table answers every look-up: 8 bytes an entry saved)
        self._n = n

    def __len__(self) -> int:
        return self._n

    def slices(self, x: float, y: float, radius_m: float) -> list[tuple[int, int]]:
        """(start, stop) of the entries of every non-empty band slice the disc's bounding box needs: one
        band for every three rows of cells it covers, the columns it covers in each."""
        cell, ncol, start = self.cell_m, self.ncol, self._start
        # (comparisons rather than min/max calls: this runs once a match, issue 21)
        c0 = math.floor((x - radius_m - self.x0) / cell)
        c1 = math.floor((x + radius_m - self.x0) / cell)
        r0 = math.floor((y - radius_m - self.y0) / cell)
        r1 = math.floor((y + radius_m - self.y0) / cell)
        if c0 < 0:
            c0 = 0
        if r0 < 0:
            r0 = 0
        if c1 >= ncol:
            c1 = ncol - 1
        if r1 >= self.nrow:
            r1 = self.nrow - 1
        if c0 > c1 or r0 > r1:
            return []
        if r1 - r0 < BAND_ROWS and start is not None:  # (the common case: one band, r0's)
            a, b = start[r0 * ncol + c0], start[r0 * ncol + c1 + 1]
            return [(a, b)] if b > a else []
        # bands r0, r0 + 3, ...: disjoint, together every row r0..r1 (the last may reach past r1, where
        # every point lies farther than the radius)
        rows = list(range(r0 * ncol, r1 * ncol + 1, BAND_ROWS * ncol))
        if start is not None:
            bounds = [(start[row + c0], start[row + c1 + 1]) for row in rows]
        else:
            first = [row + c0 for row in rows]
            assert self.key is not None
            b = np.searchsorted(self.key, first + [row + c1 + 1 for row in rows]).tolist()
            bounds = list(zip(b[:len(rows)], b[len(rows):]))
        return [s for s in bounds if s[1] > s[0]]

    def gather(self, arr: np.ndarray, sl: list[tuple[int, int]]) -> np.ndarray:
        """The entries of ``arr`` (in band order, along its last axis) the slices select, as one array
        (a view for one slice)."""
        if len(sl) == 1:
            return arr[..., sl[0][0]:sl[0][1]]
        return np.concatenate([arr[..., a:b] for a, b in sl], axis=-1)

    def point_of(self, sl: list[tuple[int, int]], k: int) -> int:
        """The point index of the k-th entry of the slices' concatenation."""
        for a, b in sl:
            if k < b - a:
                return int(self.by_cell[self.rank[a + k]])
            k -= b - a
        raise IndexError(k)

    def query(self, x: float, y: float, radius_m: float) -> np.ndarray:
        """Indices of the points within ``radius_m`` of (x, y) (distance ≤ radius), in row-major cell
        order (then by index)."""
        sl = self.slices(x, y, radius_m)
        if not sl:
            return np.empty(0, dtype=np.intp)
        z = self.gather(self.z, sl)
        dx = z.real - x
        dy = z.imag - y
        inside = np.flatnonzero(dx * dx + dy * dy <= radius_m * radius_m)
        rank = self.gather(self.rank, sl)[inside]
        rank.sort()
        return self.by_cell[rank]


def _take_rows(rows, index: np.ndarray) -> np.ndarray:
    """A (len(rows), len(index)) array of each row's entries at ``index``."""
    out = np.empty((len(rows), len(index)))
    for i, r in enumerate(rows):
        np.take(r, index, out=out[i])
    return out
