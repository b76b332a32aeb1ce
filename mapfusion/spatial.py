"""A cell index over the way-points for single radius queries (issue 21).

A k-d tree answers one ball query in 11–15 µs here (issue 21's machine), much of it spent building
a Python list of the hits. Here the points are bucketed in square cells and stored cell by cell in
row-major order, so the cells a disc covers are one contiguous slice per row of cells: a query is
a few table look-ups and slices of arrays that already hold each point's position and heading,
with no tree walk and no per-hit Python object. The k-d tree stays for the batch matcher's
k-nearest queries.
"""

from __future__ import annotations

import array
import math

import numpy as np

#: Side of a cell (m): the matcher's default radius, so a query of that radius covers 2–3 rows.
CELL_M = 20.0
#: A table of every cell's first point is kept when it has at most this many entries per point
#: (and at least this many cells are allowed): a sparse regional map falls back to a binary search.
DENSE_CELLS_PER_POINT, DENSE_CELLS_MIN = 4, 1 << 20


class CellIndex:
    """Points (N, 2) in cells of ``cell_m``; ``block`` (5, N) holds the points' x, y, their headings'
    cosines and sines and a sign (the matcher's: -1 where both directions of travel are legal, +1 where
    only the heading's) in cell order, ``order`` maps that order back to the point indices."""

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
        key = cy * self.ncol + cx
        self.order = np.argsort(key, kind="stable").astype(np.intp)
        self.key = key[self.order]
        # x, y, cos, sin, sign as the rows of one (5, N) array: a query gathers one slice a row of cells,
        # not five, and each quantity stays contiguous for numpy's loops
        sign = np.full(n, -1.0) if sign is None else np.asarray(sign, dtype=float)
        self.block = np.ascontiguousarray(np.vstack([xy[self.order, 0], xy[self.order, 1],
                                                     np.asarray(cos, dtype=float)[self.order],
                                                     np.asarray(sin, dtype=float)[self.order], sign[self.order]]))
        cells = self.ncol * self.nrow
        self._start: array.array | None = None  # (compact: a query's look-ups stay in few cache lines)
        if cells <= max(DENSE_CELLS_PER_POINT * n, DENSE_CELLS_MIN):
            self._start = array.array("q", np.searchsorted(self.key, np.arange(cells + 1)).astype(np.int64).tobytes())

    def __len__(self) -> int:
        return len(self.order)

    def slices(self, x: float, y: float, radius_m: float) -> list[tuple[int, int]]:
        """(start, stop) in cell order of every non-empty row of cells the disc's bounding box covers."""
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
        if start is not None:
            out = []
            for row in range(r0 * ncol, r1 * ncol + 1, ncol):
                a, b = start[row + c0], start[row + c1 + 1]
                if b > a:
                    out.append((a, b))
            return out
        rows = np.arange(r0 * ncol, r1 * ncol + 1, ncol)
        b = np.searchsorted(self.key, np.concatenate([rows + c0, rows + c1 + 1])).tolist()
        m = len(rows)
        return [s for s in zip(b[:m], b[m:]) if s[1] > s[0]]

    def gather(self, arr: np.ndarray, sl: list[tuple[int, int]]) -> np.ndarray:
        """The entries of ``arr`` (in cell order, along its last axis) the slices select, as one array."""
        if len(sl) == 1:
            return arr[..., sl[0][0]:sl[0][1]]
        return np.concatenate([arr[..., a:b] for a, b in sl], axis=-1)

    def point_of(self, sl: list[tuple[int, int]], k: int) -> int:
        """The point index of the k-th entry of the slices' concatenation."""
        for a, b in sl:
            if k < b - a:
                return int(self.order[a + k])
            k -= b - a
        raise IndexError(k)

    def query(self, x: float, y: float, radius_m: float) -> np.ndarray:
        """Indices of the points within ``radius_m`` of (x, y) (distance ≤ radius), in cell order."""
        sl = self.slices(x, y, radius_m)
        if not sl:
            return np.empty(0, dtype=np.intp)
        b = self.gather(self.block, sl)
        dx = b[0] - x
        dy = b[1] - y
        inside = np.flatnonzero(dx * dx + dy * dy <= radius_m * radius_m)
        return self.gather(self.order, sl)[inside]
