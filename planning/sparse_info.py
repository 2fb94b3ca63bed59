"""Candidate x target information stored only where the candidate sees the target (issue 21).

The planner's information array is ``(m, n, 6)`` float32 and zero wherever candidate ``i`` does not
see target ``t``: 3,000 candidates x 50,000 targets take 3.6 GB dense. :class:`SparseInfo` keeps the
visible pairs only, by candidate: row ``i``'s entries are ``indices[starts[i]:ends[i]]`` (targets, increasing)
and ``data[starts[i]:ends[i]]`` (``(., 6)``). Built compact (CSR: ``starts = indptr[:-1]``, ``ends = indptr[1:]``),
or as a :meth:`SparseInfo.view` whose rows point anywhere into shared buffers (the polish's pool of
ray-cast variants: no copy). It answers the row selections the planner makes (``info[i]``, ``info[rows]``,
``info[rows, cols]``, ``info[np.ix_(rows, cols)]``, ``info[:, cols, k]``) with the same dense values the
dense array would give, so every sum and every result stays bit-identical; only the selected rows are ever
materialised. The compiled kernels of :mod:`planning.kernels` work on ``starts, ends, indices, data``.
"""

from __future__ import annotations

import numpy as np

__all__ = ["SparseInfo", "add_rows", "DENSE_LIMIT_BYTES"]

# Above this size (m * n * 6 * 4 bytes) a dense information array is not made (CLOSE_LOOP, tests).
DENSE_LIMIT_BYTES = 1 << 30


class SparseInfo:
    """``(m, n, 6)`` information, non-zero only on visible pairs; rows ``[starts[i], ends[i])``."""

    ndim = 3

    def __init__(self, indptr: np.ndarray, indices: np.ndarray, data: np.ndarray, n: int):
        self.indptr = np.asarray(indptr, dtype=np.int64)
        self.indices = np.asarray(indices, dtype=np.int32)
        self.data = np.asarray(data)
        if self.data.ndim != 2 or self.data.shape[1] != 6 or len(self.data) != len(self.indices) \
                or self.indptr[-1] != len(self.indices):
            raise ValueError("SparseInfo: indptr, indices and data (nnz, 6) disagree")
        self.starts, self.ends = self.indptr[:-1], self.indptr[1:]
        self.shape = (len(self.indptr) - 1, int(n), 6)
        self.dtype = self.data.dtype
        self._row = None

    @classmethod
    def view(cls, starts: np.ndarray, ends: np.ndarray, indices: np.ndarray, data: np.ndarray, n: int) -> "SparseInfo":
        """Rows ``[starts[i], ends[i])`` of the buffers ``indices``, ``data`` (shared, not copied)."""
        self = cls.__new__(cls)
        self.indptr = None
        self.starts, self.ends = np.asarray(starts, dtype=np.int64), np.asarray(ends, dtype=np.int64)
        self.indices, self.data = indices, data
        if self.starts.shape != self.ends.shape or (len(self.ends) and self.ends.max() > len(indices)):
            raise ValueError("SparseInfo.view: rows outside the buffers")
        self.shape = (len(self.starts), int(n), 6)
        self.dtype = data.dtype
        self._row = None
        return self

    def __len__(self) -> int:
        return self.shape[0]

    @property
    def nnz(self) -> int:
        return int(np.sum(self.ends - self.starts))

    @property
    def nbytes(self) -> int:
        return self.starts.nbytes + self.ends.nbytes + self.indices.nbytes + self.data.nbytes

    def compact(self) -> "SparseInfo":
        """This information in CSR form (itself when it is already)."""
        return self if self.indptr is not None else self.select(np.arange(self.shape[0]))

    @classmethod
    def from_dense(cls, info: np.ndarray, visible: np.ndarray) -> "SparseInfo":
        ci, ti = np.nonzero(np.asarray(visible, dtype=bool))
        indptr = np.zeros(info.shape[0] + 1, dtype=np.int64)
        np.cumsum(np.bincount(ci, minlength=info.shape[0]), out=indptr[1:])
        return cls(indptr, ti, info[ci, ti], info.shape[1])

    def toarray(self) -> np.ndarray:
        return self.take(np.arange(self.shape[0]))

    def row_of_entry(self) -> np.ndarray:
        """(nnz,) the row of each entry (CSR form)."""
        c = self.compact()
        if c._row is None:
            c._row = np.repeat(np.arange(c.shape[0], dtype=np.int32), np.diff(c.indptr))
        return c._row

    def scale_targets(self, w: np.ndarray) -> "SparseInfo":
        """The information with target ``t`` multiplied by ``w[t]`` (``info * w[None, :, None]``)."""
        c = self.compact()
        w = np.asarray(w, dtype=self.dtype)
        return SparseInfo(c.indptr, c.indices, c.data * w[c.indices][:, None], self.shape[1])

    def _entries(self, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(position in ``rows``, entry index) of every stored entry of the given rows."""
        lo, hi = self.starts[rows], self.ends[rows]
        ln = hi - lo
        which = np.repeat(np.arange(len(rows)), ln)
        start = np.repeat(lo - np.concatenate([[0], np.cumsum(ln)[:-1]]), ln)
        return which, start + np.arange(int(ln.sum()))

    def take(self, rows, cols=None) -> np.ndarray:
        """Dense ``(len(rows), len(cols) or n, 6)``, equal to ``dense[rows][:, cols]``."""
        from planning import kernels

        rows = np.arange(self.shape[0])[rows].reshape(-1) if not isinstance(rows, np.ndarray) \
            else np.asarray(rows).reshape(-1)
        if rows.dtype == bool:
            rows = np.flatnonzero(rows)
        rows = np.where(rows < 0, rows + self.shape[0], rows).astype(np.intp)
        if cols is None:
            return kernels.rows_dense(self.starts, self.ends, self.indices, self.data, rows, self.shape[1])
        cols = np.arange(self.shape[1])[cols].reshape(-1) if not isinstance(cols, np.ndarray) \
            else np.asarray(cols).reshape(-1)
        if cols.dtype == bool:
            cols = np.flatnonzero(cols)
        cols = np.where(cols < 0, cols + self.shape[1], cols).astype(np.intp)
        return kernels.gather(self.starts, self.ends, self.indices, self.data, rows, cols)

    def __getitem__(self, key):
        if not isinstance(key, tuple):
            if np.ndim(key) == 0 and not isinstance(key, slice):
                return self.take(np.array([int(key)]))[0]
            return self.take(key)
        if len(key) == 3:
            return self[key[:2]][..., key[2]]
        r, c = key
        if isinstance(r, np.ndarray) and isinstance(c, np.ndarray) and r.ndim == 2 and c.ndim == 2 \
                and r.shape[1] == 1 and c.shape[0] == 1:  # np.ix_(rows, cols)
            return self.take(r[:, 0], c[0])
        if np.ndim(r) == 0 and not isinstance(r, slice):
            return self.take(np.array([int(r)]), c)[0]
        if np.ndim(c) == 0 and not isinstance(c, slice):
            return self.take(r, np.array([int(c)]))[:, 0]
        if isinstance(r, np.ndarray) and isinstance(c, np.ndarray) and r.shape == c.shape and r.ndim == 1 \
                and r.dtype != bool:
            raise TypeError("SparseInfo: paired fancy indexing is not supported")
        return self.take(r, c)

    def rows(self, rows: np.ndarray) -> "SparseInfo":
        """The candidates ``rows`` (int array) as a view sharing this information's buffers."""
        rows = np.asarray(rows, dtype=np.int64)
        return SparseInfo.view(self.starts[rows], self.ends[rows], self.indices, self.data, self.shape[1])

    def select(self, rows: np.ndarray) -> "SparseInfo":
        """The candidates ``rows`` (int array), still sparse (compact copy)."""
        rows = np.asarray(rows, dtype=np.int64)
        _, e = self._entries(rows)
        indptr = np.concatenate([[0], np.cumsum(self.ends[rows] - self.starts[rows])])
        return SparseInfo(indptr, self.indices[e], self.data[e], self.shape[1])

    @staticmethod
    def vstack(parts: list) -> "SparseInfo":
        """The candidates of ``parts`` (SparseInfo, same n) one after the other."""
        parts = [p.compact() for p in parts]
        offs = np.cumsum([0] + [len(p.indices) for p in parts])
        indptr = np.concatenate([[0]] + [p.indptr[1:] + o for p, o in zip(parts, offs)])
        return SparseInfo(indptr, np.concatenate([p.indices for p in parts]),
                          np.concatenate([p.data for p in parts]), parts[0].shape[1])

    def __array__(self, *a, **k):
        raise TypeError("SparseInfo would be made dense; use .toarray() explicitly")


def add_rows(info, acc: np.ndarray, rows: np.ndarray | None, cand: np.ndarray) -> None:
    """``acc[rows] += info[cand]`` (``rows=None``: all rows of ``acc``), dense or sparse ``info``.

    Each row of ``acc`` receives one candidate, so no (row, target) pair is added twice and the
    float32 sums equal the dense ones exactly."""
    if not isinstance(info, SparseInfo):
        if rows is None:
            acc += info[cand]
        else:
            acc[rows] += info[cand]
        return
    from planning import kernels

    cand = np.asarray(cand, dtype=np.intp)
    rows = np.arange(len(cand)) if rows is None else np.asarray(rows, dtype=np.intp)
    kernels.add_rows(info.starts, info.ends, info.indices, info.data, acc, rows, cand)
