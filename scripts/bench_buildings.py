"""Large maps and real buildings for BENCHMARKS.md: how visibility + ROI cost grows with
the map's size, and localization in the imported ground floors of the shared IFC models, with
the paper arena as the baseline.

    python scripts/bench_buildings.py [--quick]
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import math  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Dict, List, Optional, Tuple  # noqa: E402

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from drivers.sim.building import free_space_poses, grid_for_planes, room_grid_map  # noqa: E402
from drivers.sim.render import Box, DepthNoise, SimScene, random_clutter, render_depth_frame  # noqa: E402
from robot.base.geometry import pose_to_T_ground_robot  # noqa: E402
from robot.config import load_robot_config  # noqa: E402
from robot.localization.crlb import pose_crlb  # noqa: E402
from robot.localization.localizer import DEFAULT_COARSE_STD, FIX_STATUSES, Localizer  # noqa: E402
from robot.maps.plane_index import PlaneIndex  # noqa: E402
from robot.maps.plane_map import PlaneMap, load_plane_map  # noqa: E402

ROBOT = load_robot_config(ROOT / "config/robot.yaml")
PARAMS = ROBOT.localizer
IFC_DIR = ROOT.parent / "shared" / "data" / "ifc"
# Map file written by the IFC importer -> (model, storey) to import it from when it is missing.
BUILDINGS = [
    ("fzk_haus_ground.yaml", "AC20-FZK-Haus.ifc", "Erdgeschoss"),
    ("duplex_level1.yaml", "Duplex_A_20110907.ifc", "Level 1"),
    ("institute_ground.yaml", "AC11-Institute-Var-2-IFC.ifc", "Erdgeschoss"),
]
TARGET_MS = 1.0  # target: visibility + ROI of a 2,000-plane map, median per frame
RENDER_RADIUS = 12.0  # m: the renderer gets the planes this close (its depth stops at 10 m)


COLD_COV = np.diag(np.square(DEFAULT_COARSE_STD))  # the localizer's default coarse covariance


class _AllPlanes:
    """Stands in for the spatial index: every plane is a candidate (what the index saves)."""

    def __init__(self, n: int):
        self.all = list(range(n))

    def in_view(self, *_args) -> List[int]:
        return self.all


class _Counting:
    """Passes ``in_view`` through and remembers how many candidates it returned (a stand-in index:
    the localizer takes its in_view, then the numpy prediction)."""

    def __init__(self, index):
        self.index, self.last = index, 0

    def in_view(self, *args) -> List[int]:
        out = self.index.in_view(*args)
        self.last = len(out)
        return out


def visibility_and_roi(loc: Localizer, geo, T_ground_camera, cov=COLD_COV):
    """What the localizer does per frame before fitting (Localizer.plane_rois): index query,
    pre-cull, clipping, rasterization on the margin-padded grid, ROI erosion."""
    return loc.plane_rois(geo, T_ground_camera, cov)


class FrameTimer:
    """Visibility + ROI frames of one map at given poses, timed in rounds: scaling() runs a round of
    every map in turn and keeps each frame's best time, so a burst of load from other processes
    spoils one round of one map, not a whole row. ``index=None``: every plane, no index."""

    def __init__(self, plane_map: PlaneMap, index: Optional[PlaneIndex], poses, cam):
        self.loc = Localizer(ROBOT, plane_map)
        # With the index, the localizer's own (the compiled kernels take it whole); the candidates
        # are counted by a call of its in_view outside the timing.
        self.counter = _Counting(_AllPlanes(len(plane_map)) if index is None else index)
        if index is None:
            self.loc.index = self.counter
        self.geo = self.loc.frame_geometry(cam, cam.intrinsics_from_fov(), cam.width, cam.height)
        self.Ts = [pose_to_T_ground_robot(*p) @ cam.T_robot_camera for p in poses]
        self.best = np.full(len(poses), np.inf)
        self.counts = []

    def round(self) -> None:
        for i, T in enumerate(self.Ts):
            t0 = time.perf_counter()
            views = visibility_and_roi(self.loc, self.geo, T)
            self.best[i] = min(self.best[i], time.perf_counter() - t0)
            if len(self.counts) < len(self.Ts):
                if self.loc.index is not self.counter:  # once more with the counting stand-in, untimed
                    index, self.loc.index = self.loc.index, self.counter
                    visibility_and_roi(self.loc, self.geo, T)
                    self.loc.index = index
                self.counts.append((self.counter.last, len(views), sum(1 for v in views if v.box[2] >= v.box[0]),
                                    sum(1 for v in views if v.pixels > 0)))

    @property
    def ms(self) -> np.ndarray:
        return self.best * 1e3


def scaling(quick: bool) -> List[str]:
    sizes = (10, 200, 2000, 20000)
    n_poses = 25 if quick else 80
    repeats = 3 if quick else 5
    cam = ROBOT.camera("front")
    lines = ["### Visibility + ROI cost against map size", "",
             f"Synthetic floors of square 4 m rooms with a door in every inner wall (`drivers/sim_building.py`); "
             f"front camera, {cam.width}x{cam.height} at pixel stride {PARAMS.pixel_stride}, range "
             f"{PARAMS.max_range:g} m, ROI margins of a cold start (0.1 m / 10 deg); {n_poses} random poses inside "
             f"rooms per map; each frame timed as the best of {repeats} rounds over all maps (other processes share "
             "the cores). "
             "One frame = spatial-index query + frustum/back-face pre-cull + clipping + nearest-first "
             "rasterization on the grid padded by the largest margin + ROI erosion (`Localizer.plane_rois`, "
             "everything before the plane fits).", "",
             "| planes | polygons | index build (s) | candidates in view | views | rasterized | visible | "
             "median ms | p95 ms | without the index: median ms |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    rows = []
    for n in sizes:
        plane_map = room_grid_map(*grid_for_planes(n), seed=n)
        t0 = time.perf_counter()
        index = PlaneIndex(plane_map)
        build = time.perf_counter() - t0
        poses = free_space_poses(plane_map, n_poses, np.random.default_rng(n), z=0.15)
        # Without the index (every plane into predict_plane_views, the numpy code) shows what the
        # index saves; a few poses suffice.
        rows.append((plane_map, build, FrameTimer(plane_map, index, poses, cam),
                     FrameTimer(plane_map, None, poses[:max(5, n_poses // 8)], cam)))
    for r in range(repeats):
        for _, _, timer, brute in rows:
            timer.round()
            if r == 0:
                brute.round()
    medians = {}
    for plane_map, build, timer, brute in rows:
        t, c = timer.ms, np.mean(timer.counts, axis=0)
        polygons = sum(len(p.polygons) for p in plane_map.planes)
        medians[len(plane_map)] = float(np.median(t))
        lines.append(f"| {len(plane_map)} | {polygons} | {build:.2f} | {c[0]:.1f} | {c[1]:.1f} | {c[2]:.1f} | {c[3]:.1f} | "
                     f"{np.median(t):.3f} | {np.percentile(t, 95):.3f} | {np.median(brute.ms):.2f} |")
    at_2000 = min(medians, key=lambda k: abs(k - 2000))
    verdict = "met" if medians[at_2000] <= TARGET_MS else "NOT met"
    lines += ["", f"- Target: at most {TARGET_MS:g} ms median per frame for a 2,000-plane map: **{verdict}** "
              f"({medians[at_2000]:.3f} ms with {at_2000} planes).",
              "- 'candidates in view': planes the index and pre-cull pass to clipping; 'rasterized': planes "
              "that were drawn (the others were found hidden behind nearer walls from their box alone); "
              "'visible': planes that own pixels."]
    return lines


def import_building(name: str, model: str, storey: str, tmp: Path) -> Tuple[Optional[PlaneMap], str]:
    """The importer's map from config/maps, else one imported now into ``tmp`` (benchmark only)."""
    path = ROOT / "config" / "maps" / name
    if path.exists():
        return load_plane_map(path), f"config/maps/{name}"
    src = IFC_DIR / model
    if not src.exists():
        return None, f"no {path} and no {src}"
    out = tmp / name
    robotctl = Path(sys.executable).parent / "robotctl"
    cmd = [str(robotctl), "map", "import-ifc", str(src), "--storey", storey, "--out", str(out)]
    res = subprocess.run(cmd, capture_output=True, text=True)
    if res.returncode != 0 or not out.exists():
        last = ((res.stderr or res.stdout).strip().splitlines() or ["no output"])[-1]
        return None, f"import of {model} failed: {last}"
    return load_plane_map(out), f"imported now from {model} ('{storey}'), config/maps/{name} was missing"


def coarse_from(truth, rng) -> Tuple[float, float, float]:
    """0.1 m off in a random direction and 10 degrees off to a random side."""
    a = rng.uniform(0, 2 * math.pi)
    return (truth[0] + 0.1 * math.cos(a), truth[1] + 0.1 * math.sin(a),
            truth[2] + math.radians(10.0) * (1 if rng.random() < 0.5 else -1))


def identification(plane_map: PlaneMap, res, truth) -> Tuple[int, int, int]:
    """(used, wrong, off) counts over the planes the localizer used, from its fit in the robot frame
    against the claimed plane at the true pose.

    Off: normal more than 3 deg or offset more than 3 cm away (the arena benchmark's test). For a
    far wall seen on a small patch, a noisy normal moves the offset extrapolated back to the robot
    by centimetres, so off also counts fits of the right wall that are just noisy. Wrong: off, and
    also more than 5 standard deviations of the fit's own covariance away: a fit to something else.
    """
    used = [p for p in res.planes if p.used]
    wrong = off = 0
    c, s = math.cos(truth[2]), math.sin(truth[2])
    for p, m in zip(used, res.measurements):
        pl = plane_map[p.id]
        n_true = np.array([c * pl.normal[0] + s * pl.normal[1], -s * pl.normal[0] + c * pl.normal[1], pl.normal[2]])
        angle = math.acos(min(1.0, float(n_true @ np.asarray(p.normal))))
        e = m.residual(*truth)
        if angle > math.radians(3) or abs(e[0]) > 0.03:
            off += 1
            if abs(e[0]) > max(0.03, 5 * math.sqrt(m.R[0, 0])) or abs(e[1]) > max(math.radians(3), 5 * math.sqrt(m.R[1, 1])):
                wrong += 1
    return len(used), wrong, off


def normalized_error(res, truth, bound: np.ndarray) -> float:
    """Position error in units of the Cramer-Rao bound at the localizer's pixel stride (a stride s
    uses 1/s^2 of the pixels): sqrt(e^T (s^2 C)^-1 e); an efficient estimator gives a chi(2)
    variable (median 1.18, p95 2.45)."""
    e = np.array([res.x - truth[0], res.y - truth[1]])
    C = bound[:2, :2] * PARAMS.pixel_stride ** 2
    return float(math.sqrt(e @ np.linalg.solve(C, e)))


def two_walls(plane_map: PlaneMap, res, truth, near: float = 3.0) -> Tuple[bool, bool]:
    """Whether two used walls have normals at least 20 degrees apart (position fixed in both axes),
    and whether two such walls are both within ``near`` metres of the robot."""
    used = {p.id for p in res.planes if p.used}
    walls = [(plane_map[i].normal[:2], abs(plane_map[i].normal[:2] @ truth[:2] + plane_map[i].d)) for i in used]
    any_pair = near_pair = False
    for i in range(len(walls)):
        for j in range(i):
            (a, da), (b, db) = walls[i], walls[j]
            if abs(a[0] * b[1] - a[1] * b[0]) / (np.linalg.norm(a) * np.linalg.norm(b)) > math.sin(math.radians(20)):
                any_pair = True
                near_pair = near_pair or max(da, db) <= near
    return any_pair, near_pair


def render_scene(plane_map: PlaneMap, index: PlaneIndex, camera_G: np.ndarray, clutter) -> SimScene:
    """The simulated world one camera at ``camera_G`` sees: the map's wall faces within RENDER_RADIUS
    (the renderer tests every polygon it is given and its depth ends at 10 m), floor, backdrop and
    clutter. Map faces are one-sided in the renderer: a face seen from behind is not drawn."""
    near = [plane_map.planes[i] for i in index.candidates(camera_G[:2], RENDER_RADIUS)]
    boxes = [b for b in clutter if math.hypot(b.x - camera_G[0], b.y - camera_G[1]) < RENDER_RADIUS]
    return SimScene(PlaneMap(near or plane_map.planes[:1], source=plane_map.source), boxes)


def localize_in(plane_map: PlaneMap, n_poses: int, seed: int) -> Dict:
    rng = np.random.default_rng(seed)
    loc = Localizer(ROBOT, plane_map)
    index = loc.index
    poses = free_space_poses(plane_map, n_poses, rng, clearance=0.4, z=0.15)
    lo, hi = plane_map.bounds()
    area = float(np.prod(hi[:2] - lo[:2]))
    geos = {c.name: loc.frame_geometry(c, c.intrinsics_from_fov(), c.width, c.height) for c in ROBOT.cameras}
    rows = []
    vis_ms = []
    for k, truth in enumerate(poses):
        # Clutter the map does not know: about one box per 4 m^2 of floor, at least two near the robot.
        clutter = random_clutter(plane_map, max(2, int(area / 4.0)), rng, keep_clear=[truth[:2]], clearance=0.35)
        ring = [(truth[0] + r * math.cos(a), truth[1] + r * math.sin(a))
                for r, a in zip(rng.uniform(0.6, 2.5, 2), rng.uniform(0, 2 * math.pi, 2))]
        clutter += [Box(x, y, *rng.uniform(0.05, 0.25, 3), rng.uniform(0, math.pi)) for x, y in ring]
        frames = []
        for c in ROBOT.cameras:
            cam_G = (pose_to_T_ground_robot(*truth) @ c.T_robot_camera)[:3, 3]
            scene = render_scene(plane_map, index, cam_G, clutter)
            frames.append(render_depth_frame(ROBOT, scene, c.name, truth, rng=rng, frame_number=k))
        coarse = coarse_from(truth, rng)
        for cam in ROBOT.cameras:
            T = pose_to_T_ground_robot(*coarse) @ cam.T_robot_camera
            best = math.inf
            for _ in range(3):
                t0 = time.perf_counter()
                visibility_and_roi(loc, geos[cam.name], T)
                best = min(best, time.perf_counter() - t0)
            vis_ms.append(best * 1e3)
        res = loc.localize(frames, coarse)
        e = np.array([res.x - truth[0], res.y - truth[1], math.remainder(res.phi - truth[2], 2 * math.pi)])
        nees = float(e @ np.linalg.solve(res.cov, e)) if res.status in FIX_STATUSES else None
        used, wrong, off = identification(plane_map, res, truth)
        two, two_near = two_walls(plane_map, res, truth)
        bound = None
        if two and res.status in FIX_STATUSES:
            try:
                bound = pose_crlb(ROBOT, plane_map, truth, DepthNoise())
            except np.linalg.LinAlgError:
                pass  # the walls the localizer used are not all in view at the true pose
        err_mm = 1000 * math.hypot(res.x - truth[0], res.y - truth[1])
        err_deg = abs(math.degrees(math.remainder(res.phi - truth[2], 2 * math.pi)))
        rows.append({"truth": truth, "status": res.status, "err_mm": err_mm, "err_deg": err_deg, "off": off,
                     "wrong": wrong, "two": two, "two_near": two_near, "unobservable": res.unobservable, "used": used, "ms": res.ms,
                     "nerr": None if bound is None else normalized_error(res, truth, bound), "nees": nees})
    return {"rows": rows, "vis_ms": np.array(vis_ms), "poses": len(poses)}


def _stat(values) -> str:
    v = np.asarray([x for x in values if x is not None], float)
    if len(v) == 0:
        return "-"
    return f"{np.median(v):.2f} / {np.percentile(v, 95):.2f}"


def _nees(values) -> str:
    v = np.asarray([x for x in values if x is not None], float)
    if len(v) == 0:
        return "-"
    return f"{np.mean(v):.2f} / {np.median(v):.2f} / {np.percentile(v, 95):.2f}"


ARENA_TARGET = (3.0, 0.2)  # mm, deg: the arena's static-accuracy target (scripts/bench_localizer.py)


def buildings(quick: bool) -> List[str]:
    n_poses = 10 if quick else 40
    intro = ["### Localization inside the imported buildings", "",
             f"Ground floors imported from the shared IFC models by `robotctl map import-ifc`, the paper arena as the "
             f"baseline. Per map {n_poses} poses sampled in free space (at least 0.4 m from every wall face, inside "
             "rooms and corridors: rays cast from the point must meet walls from their front), random heading; both "
             "cameras rendered with the realistic D435i model (docs/simulator.md), the floor, a backdrop and clutter "
             "boxes the map does not know (about "
             "one per 4 m^2 plus two within 2.5 m of the robot); localized (joint method) from a coarse pose 0.1 m "
             "off in a random direction and 10 deg off, with the localizer's default coarse covariance. Errors are "
             "over poses with status ok. Used planes: 'off' when the fit in the robot frame is more than 3 deg or "
             "3 cm from the claimed plane at the true pose, 'wrong' when it is also more than 5 standard deviations "
             "of the fit's own covariance away (a fit to some other surface).", "",
             "| map | planes | polygons | poses | visibility + ROI ms per frame (median / p95) | status ok / unprotected / "
             "degenerate / no planes | pos err mm (median / p95) | heading err deg (median / p95) | planes used / "
             "wrong / off | localize ms (median) |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    pairs = ["", "Poses where two used walls are at least 20 deg apart, all of them and those where both walls "
             "are within 3 m. 'err / bound': position error in units of the pose's Cramer-Rao bound at the "
             "localizer's pixel stride (`robot/crlb.py`, every pixel of the visible walls, no clutter; an efficient "
             "estimator gives median 1.18, p95 2.45). 'NEES': the pose error in units of the covariance the localizer "
             "reported, e^T C^-1 e over (x, y, phi): an honest covariance gives mean 3, median 2.37, p95 7.81; "
             "larger means the localizer claims more accuracy than it has.", "",
             "| map | walls | poses | pos err mm (median / p95) | heading err deg (median / p95) | err / bound "
             "(median / p95) | NEES mean / median / p95 |", "|---|---|---|---|---|---|---|"]
    notes = []
    summary = {}
    with tempfile.TemporaryDirectory() as tmp:
        maps = [("paper arena (baseline)", load_plane_map(ROOT / "config/maps/paper_arena.yaml"), "config/maps/paper_arena.yaml")]
        for name, model, storey in BUILDINGS:
            pm, where = import_building(name, model, storey, Path(tmp))
            maps.append((name.replace(".yaml", ""), pm, where))
        for label, pm, where in maps:
            if pm is None:
                intro.append(f"| {label} | - | - | - | not run: {where} | | | | | |")
                continue
            if "imported now" in where:
                notes.append(f"- {label}: {where}.")
            out = localize_in(pm, n_poses, seed=sum(map(ord, label)))
            rows = out["rows"]
            ok = [r for r in rows if r["status"] in FIX_STATUSES]
            statuses = [sum(1 for r in rows if r["status"] == s) for s in ("ok", "unprotected", "degenerate", "no_planes")]
            counts = [sum(r[k] for r in rows) for k in ("used", "wrong", "off")]
            intro.append(
                f"| {label} | {len(pm)} | {sum(len(p.polygons) for p in pm.planes)} | {out['poses']} | "
                f"{_stat(out['vis_ms'])} | {' / '.join(map(str, statuses))} | {_stat([r['err_mm'] for r in ok])} | "
                f"{_stat([r['err_deg'] for r in ok])} | {' / '.join(map(str, counts))} | "
                f"{np.median([r['ms'] for r in rows]):.1f} |")
            for key, what in (("two", "two, any range"), ("two_near", "two within 3 m")):
                sel = [r for r in ok if r[key]]
                summary[(label, key)] = sel
                pairs.append(f"| {label} | {what} | {len(sel)} | {_stat([r['err_mm'] for r in sel])} | "
                             f"{_stat([r['err_deg'] for r in sel])} | {_stat([r['nerr'] for r in sel])} | "
                             f"{_nees([r['nees'] for r in sel])} |")
            degenerate = [r for r in rows if r["status"] == "degenerate"]
            if degenerate:
                r = degenerate[0]
                labels = ", ".join(u["label"] for u in r["unobservable"])
                notes.append(f"- {label}: {len(degenerate)} degenerate pose(s) found, e.g. at "
                             f"({r['truth'][0]:.2f}, {r['truth'][1]:.2f}, {math.degrees(r['truth'][2]):.0f} deg) with "
                             f"{r['used']} plane(s) used, unobservable: {labels}.")
            bad = [r for r in ok if r["err_mm"] > 50 or r["err_deg"] > 2]
            if bad:
                r = max(bad, key=lambda q: q["err_mm"])
                notes.append(f"- {label}: {len(bad)} pose(s) with status ok but more than 50 mm or 2 deg off, worst at "
                             f"({r['truth'][0]:.2f}, {r['truth'][1]:.2f}, {math.degrees(r['truth'][2]):.0f} deg): "
                             f"{r['err_mm']:.0f} mm, {r['err_deg']:.2f} deg, {r['wrong']} wrong plane(s).")
    lines = intro + pairs + [""]
    base = summary.get(("paper arena (baseline)", "two"))
    for (label, key), sel in summary.items():
        if label.startswith("paper arena") or not sel or not base:
            continue
        mm, deg = np.array([r["err_mm"] for r in sel]), np.array([r["err_deg"] for r in sel])
        target = np.median(mm) <= ARENA_TARGET[0] and np.median(deg) <= ARENA_TARGET[1]
        ratio = np.median(mm) / max(np.median([r["err_mm"] for r in base]), 1e-9)
        nn = [r["nerr"] for r in sel if r["nerr"] is not None]
        b_n = [r["nerr"] for r in base if r["nerr"] is not None]
        n_ratio = np.median(nn) / np.median(b_n) if nn and b_n else float("nan")
        nees = np.mean([r["nees"] for r in sel])
        lines.append(f"- {label}, {'two walls' if key == 'two' else 'two walls within 3 m'}: the arena's accuracy "
                     f"target (median <= {ARENA_TARGET[0]:g} mm and <= {ARENA_TARGET[1]:g} deg) "
                     f"**{'met' if target else 'NOT met'}**; median position error {ratio:.0f}x the arena's in mm, "
                     f"{n_ratio:.1f}x in units of the Cramer-Rao bound; mean NEES {nees:.2f} (these scenes draw no depth "
                     "scale, mount or as-built error, which the reported covariance must still cover at their "
                     "configured uncertainty: well under 3 is the expected, conservative value here; the integrity "
                     "section measures NEES with those errors drawn).")
    lines += ["- Why millimetres cannot match the arena's: its walls are 0.3 to 1.5 m away, a building's 1 to 6 m, and "
              "depth noise grows with distance squared; the bound-normalized ratio takes that out, but the bound "
              "counts every pixel of every visible wall while the localizer uses ROIs shrunk by the cold start's "
              "margins (up to 40 px), which cost a small far wall most of its pixels."]
    lines += notes
    lines.append("- Each camera's scene holds the map's faces within 12 m (the renderer tests every polygon it is "
                 "given, and its depth ends at 10 m). The renderer draws map faces from their front only: the back of "
                 "a wall's far face, seen through a door cut in its near face, is where a real camera sees the door's "
                 "reveal, which the map leaves out.")
    return lines


def run(quick: bool = False) -> str:
    import platform

    parts = ["## Large maps and real buildings", "",
             f"_Machine: {platform.processor() or platform.machine()}, {os.cpu_count()} logical cores shared with "
             f"other work, Python {platform.python_version()}, numpy {np.__version__}; single thread._", ""]
    for fn in (scaling, buildings):
        t0 = time.perf_counter()
        parts += fn(quick)
        parts += ["", f"_({fn.__name__}: {time.perf_counter() - t0:.1f} s to measure)_", ""]
    return "\n".join(parts)


if __name__ == "__main__":
    print(run(quick="--quick" in sys.argv))
