"""The agent's geometric map: ``cell_number x cell_number x 4`` cells ``[x, y, height, rock]``.

Cell ``[i, j]`` is centred at ``(c_i, c_j)`` with ``c = -map_size/2 + cell_size/2 + k
cell_size``; the site frame is the leaderboard's right-handed world frame (the lander near
the origin). Uncompleted heights and rock flags are ``-inf`` (the leaderboard writes
``np.NINF``, which numpy 2 removed). Out-of-range positions or indexes: getters return
``None`` (``(None, None)`` for ``get_cell_data``), setters ``False``. The statistics read
``get_map_array()``, so writing the array directly counts too.
"""

from __future__ import annotations

import numpy as np

ROCK_UNCOMPLETED_VALUE = -np.inf
MAP_UNCOMPLETED_VALUE = -np.inf


def cell_centres(constants) -> np.ndarray:
    return (
        -constants.map_size / 2
        + constants.cell_size / 2
        + constants.cell_size * np.arange(constants.cell_number)
    )


def create_base_map(constants) -> np.ndarray:
    c = cell_centres(constants)
    m = np.empty((constants.cell_number, constants.cell_number, 4))
    m[:, :, 0] = c[:, None]
    m[:, :, 1] = c[None, :]
    m[:, :, 2] = MAP_UNCOMPLETED_VALUE
    m[:, :, 3] = ROCK_UNCOMPLETED_VALUE
    return m


class GeometricMap:
    def __init__(self, constants):
        self._map = create_base_map(constants)
        self._map_size = constants.map_size
        self._cell_size = constants.cell_size
        self._cell_number = constants.cell_number

    def _is_cell_valid(self, i, j) -> bool:
        return all(k is not None and 0 <= k < self._cell_number for k in (i, j))

    def get_map_array(self) -> np.ndarray:
        return self._map

    def get_map_size(self):
        return self._map_size

    def get_cell_size(self):
        return self._cell_size

    def get_cell_number(self):
        return self._cell_number

    def _index(self, v: float):
        centres = self._map[:, 0, 0]
        half = self._cell_size / 2
        k = int(np.sum(centres < v - half))
        if k == 0 and abs(centres[0] - v) > half:
            return None
        if k == self._cell_number and abs(centres[-1] - v) > half:
            return None
        return k

    def get_cell_indexes(self, x, y):
        """The indexes of the cell nearest (x, y); an index is None outside the map."""
        return self._index(x), self._index(y)

    def get_cell_data(self, x_index, y_index):
        if not self._is_cell_valid(x_index, y_index):
            return None, None
        return self._map[x_index, y_index, :2], self._cell_size

    def get_cell_height(self, x_index, y_index):
        return self._map[x_index, y_index, 2] if self._is_cell_valid(x_index, y_index) else None

    def set_cell_height(self, x_index, y_index, height) -> bool:
        if not self._is_cell_valid(x_index, y_index):
            return False
        self._map[x_index, y_index, 2] = height
        return True

    def get_height(self, x, y):
        return self.get_cell_height(*self.get_cell_indexes(x, y))

    def set_height(self, x, y, height) -> bool:
        return self.set_cell_height(*self.get_cell_indexes(x, y), height)

    def get_cell_rock(self, x_index, y_index):
        if not self._is_cell_valid(x_index, y_index):
            return None
        v = self._map[x_index, y_index, 3]
        return v if v == ROCK_UNCOMPLETED_VALUE else bool(v)

    def set_cell_rock(self, x_index, y_index, rock_flag) -> bool:
        if not self._is_cell_valid(x_index, y_index):
            return False
        self._map[x_index, y_index, 3] = rock_flag
        return True

    def get_rock(self, x, y):
        return self.get_cell_rock(*self.get_cell_indexes(x, y))

    def set_rock(self, x, y, rock_flag) -> bool:
        return self.set_cell_rock(*self.get_cell_indexes(x, y), rock_flag)
