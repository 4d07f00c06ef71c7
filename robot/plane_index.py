"""Spatial index over map planes so visibility never tests every plane of a large map.

Planes are bucketed in a uniform 2-D grid over their footprint (x, y extent); a query returns
the planes whose cells intersect the disc of the camera's useful range. For the paper arena
this is all four walls; on a building floor it is the handful of rooms around the robot.
"""

from __future__ import annotations

import math
from typing import Dict, List, Tuple

import numpy as np

from robot.plane_map import PlaneMap


class PlaneIndex:
    def __init__(self, plane_map: PlaneMap, cell: float = 2.0):
        self.cell = cell
        self.n = len(plane_map)
        self._lo = np.array([np.min(p.vertices[:, :2], axis=0) for p in plane_map.planes])
        self._hi = np.array([np.max(p.vertices[:, :2], axis=0) for p in plane_map.planes])
        self._cells: Dict[Tuple[int, int], List[int]] = {}
        for i in range(self.n):
            (i0, j0), (i1, j1) = self._cell_of(self._lo[i]), self._cell_of(self._hi[i])
            for a in range(i0, i1 + 1):
                for b in range(j0, j1 + 1):
                    self._cells.setdefault((a, b), []).append(i)

    def _cell_of(self, xy) -> Tuple[int, int]:
        return int(math.floor(xy[0] / self.cell)), int(math.floor(xy[1] / self.cell))

    def candidates(self, position, max_range: float) -> List[int]:
        """Indices (sorted) of planes whose footprint box lies within ``max_range`` of ``position``."""
        (i0, j0) = self._cell_of((position[0] - max_range, position[1] - max_range))
        (i1, j1) = self._cell_of((position[0] + max_range, position[1] + max_range))
        found = set()
        for a in range(i0, i1 + 1):
            for b in range(j0, j1 + 1):
                found.update(self._cells.get((a, b), ()))
        if not found:
            return []
        idx = np.fromiter(found, dtype=np.intp)
        # Exact test: distance from the point to each candidate's footprint box.
        p = np.asarray(position[:2], float)
        gap = np.maximum(np.maximum(self._lo[idx] - p, p - self._hi[idx]), 0.0)
        keep = np.einsum("ij,ij->i", gap, gap) <= max_range * max_range
        return sorted(idx[keep].tolist())
