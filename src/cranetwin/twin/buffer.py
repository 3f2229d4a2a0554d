"""Rows of a stream indexed by a global sample index, for :class:`cranetwin.twin.TwinStream`."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from cranetwin.errors import TwinError

F64 = npt.NDArray[np.float64]


class RowBuffer:
    """Rows indexed by a global sample index k: rows [base, base + len), stored with spare
    capacity so that appending does not copy the whole buffer each time."""

    def __init__(self, width: int) -> None:
        self.base = 0
        self._data = np.empty((0, width))
        self._n = 0

    @property
    def arr(self) -> F64:
        return self._data[: self._n]

    @property
    def end(self) -> int:
        return self.base + self._n

    def append(self, rows: F64) -> None:
        rows = rows.reshape(rows.shape[0], -1)
        need = self._n + rows.shape[0]
        if need > self._data.shape[0]:
            grown = np.empty((max(need, 2 * self._data.shape[0]), self._data.shape[1]))
            grown[: self._n] = self._data[: self._n]
            self._data = grown
        self._data[self._n : need] = rows
        self._n = need

    def get(self, k0: int, k1: int) -> F64:
        if k0 < self.base or k1 > self.end:
            raise TwinError(f"internal: rows {k0}..{k1} outside buffer {self.base}..{self.end}")
        return self._data[k0 - self.base : k1 - self.base]

    def trim(self, keep_from: int) -> None:
        cut = keep_from - self.base
        if cut > 0:
            rest = self._n - cut
            self._data[:rest] = self._data[cut : self._n].copy()
            self._n = rest
            self.base = keep_from
