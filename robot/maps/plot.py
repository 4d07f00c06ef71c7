"""Floor plan of a plane map as a PNG (matplotlib, optional extra ``viz``).

Seen from above, a vertical plane is a line. Each plane is drawn as the horizontal extent of each
of its polygons (thin), its edges along the plane's bottom (bold, so doors show as gaps), a tick
on its observable side and its id. Other planes (floors, ramps) are
drawn as faint outlines.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Optional

import numpy as np

from robot.base.errors import ConfigError
from robot.maps.plane_map import PlaneMap

VIZ_HINT = "the floor plan needs matplotlib: pip install .[viz]"


def _pyplot():
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        raise ConfigError(VIZ_HINT) from None
    return plt


def save_floor_plan(plane_map: PlaneMap, path, title: Optional[str] = None, labels: bool = True) -> Path:
    """Draw the map from above into ``path`` (PNG); returns the path."""
    plt = _pyplot()
    lo, hi = plane_map.bounds()
    size = np.maximum(hi[:2] - lo[:2], 1.0)
    scale = min(16.0 / size[0], 16.0 / size[1], 2.0)  # inches per metre, figure at most 16 in wide
    fig, ax = plt.subplots(figsize=(max(4.0, size[0] * scale + 1.5), max(4.0, size[1] * scale + 1.5)))
    n = len(plane_map)
    font = max(3.0, min(8.0, 400.0 / max(n, 1)))
    tick = 0.04 * float(max(size))
    cmap = plt.get_cmap("tab10")  # dark enough to read on white
    for k, p in enumerate(plane_map.planes):
        colour = cmap(k % 10)
        if abs(float(p.normal[2])) > math.sin(math.radians(1.0)):
            for poly in p.polygons:
                ring = np.vstack([poly, poly[:1]])
                ax.plot(ring[:, 0], ring[:, 1], color="0.8", lw=0.5, zorder=1)
            continue
        nh = p.normal[:2] / np.linalg.norm(p.normal[:2])
        along = np.array([-nh[1], nh[0]])
        mids = []
        z_floor = p.vertices[:, 2].min()
        for poly in p.polygons:
            s = poly[:, :2] @ along
            base = poly[0, :2] - (poly[0, :2] @ along) * along
            a, b = base + s.min() * along, base + s.max() * along
            ax.plot([a[0], b[0]], [a[1], b[1]], color=colour, lw=0.5, solid_capstyle="butt", zorder=2)
            mids.append((a + b) / 2)
            # Edges on the plane's bottom bold: doors show as gaps in the bold line.
            nxt = np.roll(poly, -1, axis=0)
            low = (poly[:, 2] <= z_floor + 0.05) & (nxt[:, 2] <= z_floor + 0.05)
            for v0, v1 in zip(poly[low], nxt[low]):
                ax.plot([v0[0], v1[0]], [v0[1], v1[1]], color=colour, lw=1.6, solid_capstyle="butt", zorder=2)
        mid = np.mean(mids, axis=0)
        ax.plot([mid[0], mid[0] + tick * nh[0]], [mid[1], mid[1] + tick * nh[1]], color=colour, lw=0.8, zorder=2)
        if labels:
            pos = mid + 1.6 * tick * nh
            ax.text(pos[0], pos[1], p.id, fontsize=font, color=colour, ha="center", va="center", zorder=3)
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.grid(True, lw=0.3, alpha=0.5)
    ax.set_title(title or f"{plane_map.source}: {n} planes, z {lo[2]:.2f}..{hi[2]:.2f} m", fontsize=9)
    fig.tight_layout()
    return save_figure(plt, fig, path, "the floor plan")


def save_figure(plt, fig, path, what: str = "the figure") -> Path:
    """Write ``fig`` as a PNG and close it; a path that cannot be written is one clear error."""
    out = Path(path)
    try:
        fig.savefig(out, dpi=120)
    except OSError as e:
        raise ConfigError(f"{out}: cannot write {what}: {e}") from None
    finally:
        plt.close(fig)
    return out
