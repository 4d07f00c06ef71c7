"""The simulated D435i's depth errors and the construction-site clutter, against the figures they model."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from drivers.sim.building import room_grid_map
from drivers.sim.clutter import (
    SITE_KINDS,
    Solid,
    WallDeviation,
    as_built,
    built_walls,
    door_leaf,
    leaning_boards,
    map_openings,
    pallet,
    parallel_panel,
    person,
    random_site_clutter,
    shelving,
    wall_frame,
)
from drivers.sim.render import DepthNoise, SimScene, render_depth_frame, render_depth_metres, resolve_noise
from robot.base.errors import ConfigError
from robot.base.geometry import pose_to_T_ground_robot
from robot.cli.main import main
from robot.config import load_robot_config
from robot.maps.plane_map import PlaneMap, make_plane
from robot.recording.snapshot import load_snapshot

ROBOT = load_robot_config("config/robot.yaml")
CAM = ROBOT.camera("front")  # at (0.10, 0.0175, 0.12) on the robot, looking along +x
K = CAM.intrinsics_from_fov()
FX = float(K[0, 0])
T_GC = pose_to_T_ground_robot(0.0, 0.0, 0.0) @ CAM.T_robot_camera
CAM_X = float(T_GC[0, 3])
FINE = 1e-4  # m per depth unit in these tests, so 1 mm rounding does not hide sub-millimetre effects
# Only the matcher's random error: for measuring it alone.
RANDOM_ONLY = DepthNoise.realistic(wave_px=0.0, nonlinearity_px=0.0, dropout=0.0, blobs=0.0, flying_pixels=0.0)


def wall_at(distance: float, height: float = 3.0, half_width: float = 8.0, bottom: float = -1.0) -> PlaneMap:
    """A wall facing the front camera ``distance`` m ahead of it (normal -x)."""
    x = CAM_X + distance
    return PlaneMap([make_plane("wall", [[[x, half_width, bottom], [x, -half_width, bottom], [x, -half_width, height],
                                         [x, half_width, height]]])])


def depth(scene, noise, seed=0, decimation=1, camera="front", pose=(0.0, 0.0, 0.0)):
    f = render_depth_frame(ROBOT, scene, camera, pose, rng=np.random.default_rng(seed), noise=noise,
                           depth_scale=FINE, decimation=decimation)
    return f.depth.astype(float) * FINE


def points_G(z, K_=K, T=T_GC):
    """Ground-frame points of every pixel with depth > 0, and their (row, col)."""
    rr, cc = np.nonzero(z > 0)
    d = z[rr, cc]
    p_C = np.column_stack([(cc - K_[0, 2]) / K_[0, 0] * d, (rr - K_[1, 2]) / K_[1, 1] * d, d])
    return p_C @ T[:3, :3].T + T[:3, 3], rr, cc


def plane_residual(patch):
    """Residual of a least-squares plane in (row, col) through the valid pixels of ``patch``."""
    rr, cc = np.nonzero(patch > 0)
    A = np.column_stack([rr, cc, np.ones_like(rr)]).astype(float)
    coef, *_ = np.linalg.lstsq(A, patch[rr, cc], rcond=None)
    res = np.full(patch.shape, np.nan)
    res[rr, cc] = patch[rr, cc] - A @ coef
    return res


def autocorrelation(res, lag):
    a, b = res[:, :-lag], res[:, lag:]
    m = np.isfinite(a) & np.isfinite(b)
    return float(np.corrcoef(a[m], b[m])[0, 1])


# -- random error -----------------------------------------------------------------------------------


@pytest.mark.parametrize("z", [0.5, 1.0, 2.0, 3.0])
def test_flat_wall_noise_follows_the_disparity_model(z):
    # sigma_z = z^2 s / (f_x b): 0.9 mm at 0.5 m, 3.6 mm at 1 m, 14 mm at 2 m (s = 0.08 px, f_x = 447 px).
    scene = SimScene(wall_at(z), floor=False, backdrop=False)
    model = DepthNoise.realistic().sigma(z, FX)
    stds = [np.nanstd(plane_residual(depth(scene, DepthNoise.realistic(), seed=s)[190:290, 374:474])) for s in range(4)]
    assert np.mean(stds) == pytest.approx(model, rel=0.2)


def test_noise_is_correlated_over_the_matchers_window_so_averaging_gains_less():
    scene = SimScene(wall_at(1.0), floor=False, backdrop=False)
    real = plane_residual(depth(scene, RANDOM_ONLY)[140:340, 324:524])
    simple = plane_residual(depth(scene, DepthNoise.simple(dropout=0.0, flying_pixels=0.0))[140:340, 324:524])
    lags = range(1, 12)
    corr = [autocorrelation(real, k) for k in lags]
    length = next(k for k, c in zip(lags, corr) if c < 1 / math.e)  # first lag below 1/e
    assert length > 1 and corr[0] > 0.6
    assert abs(autocorrelation(simple, 1)) < 0.05  # the kind model: independent pixels
    # The mean of an 8 x 8 block: independent noise would shrink by 8; correlated noise much less.
    blocks = real[:200, :200].reshape(25, 8, 25, 8).mean(axis=(1, 3))
    assert np.nanstd(blocks) > 3 * np.nanstd(real) / 8


def test_a_decimated_frame_keeps_most_of_the_noise():
    # librealsense's decimation averages 4 x 4 blocks of correlated noise: most of it stays.
    scene = SimScene(wall_at(1.0), floor=False, backdrop=False)
    full = np.nanstd(plane_residual(depth(scene, RANDOM_ONLY)[160:320, 344:504]))
    dec = np.nanstd(plane_residual(depth(scene, RANDOM_ONLY, decimation=4)[40:80, 86:126]))
    assert 0.6 * full < dec < 0.95 * full


# -- systematic error -------------------------------------------------------------------------------

WAVE_ONLY = replace(RANDOM_ONLY, subpixel=0.0, wave_px=0.015)


def test_the_wave_is_a_fixed_smooth_deviation_of_a_few_mm_at_2_m_growing_with_range():
    res = {}
    for z in (1.0, 2.0):
        scene = SimScene(wall_at(z, height=4.0, half_width=10.0), floor=False, backdrop=False)
        res[z] = plane_residual(depth(scene, WAVE_ONLY, seed=1))
    rms2 = float(np.sqrt(np.nanmean(res[2.0] ** 2)))
    assert 0.001 < rms2 < 0.006  # a few millimetres at 2 m, after the best plane is taken out
    # a disparity error: four times the depth error at twice the range
    assert rms2 == pytest.approx(4 * float(np.sqrt(np.nanmean(res[1.0] ** 2))), rel=0.1)
    # smooth over large parts of the image: neighbours 50 pixels apart still agree
    assert autocorrelation(res[2.0], 50) > 0.5
    # fixed to the camera unit: the same with another frame's random draws, another with another unit
    scene = SimScene(wall_at(2.0, height=4.0, half_width=10.0), floor=False, backdrop=False)
    again = plane_residual(depth(scene, WAVE_ONLY, seed=7))
    other = plane_residual(depth(scene, replace(WAVE_ONLY, unit_seed=3), seed=1))
    assert np.nanmax(np.abs(again - res[2.0])) < 2e-4
    assert np.sqrt(np.nanmean((other - res[2.0]) ** 2)) > 0.5 * rms2


def test_subpixel_nonlinearity_is_periodic_in_disparity():
    a = 0.02
    only = replace(RANDOM_ONLY, subpixel=0.0, wave_px=0.0, nonlinearity_px=a)
    fb = FX * 0.05
    for frac, sign in ((0.25, 1.0), (0.75, -1.0)):
        z = fb / (22.0 + frac)  # disparity 22.25 px: the error is +a px; 22.75 px: -a px
        scene = SimScene(wall_at(z), floor=False, backdrop=False)
        err = np.median(depth(scene, only)[200:280, 400:480]) - z
        assert err == pytest.approx(-sign * a * z * z / fb, rel=0.1)  # more disparity reads nearer


def test_scale_error_scales_depth_per_camera():
    scene = SimScene(wall_at(1.5), backdrop=False)
    base = depth(scene, DepthNoise.realistic(), seed=4)
    longer = depth(scene, DepthNoise.realistic(scale_error=0.01), seed=4)
    both = (base > 0) & (longer > 0)
    assert both.mean() > 0.8
    assert np.median(longer[both] / base[both]) == pytest.approx(1.01, abs=2e-4)
    exact = depth(scene, None)
    assert np.allclose(depth(scene, resolve_noise("none", 0.01))[exact > 0], 1.01 * exact[exact > 0], atol=FINE)
    per_camera = DepthNoise.realistic(scale_error={"left": -0.02})
    assert per_camera.scale_error_of("front") == 0.0 and per_camera.scale_error_of("left") == -0.02
    assert np.array_equal(depth(scene, per_camera, seed=4), base)
    with pytest.raises(ConfigError, match="scale error"):
        DepthNoise.realistic(scale_error=0.7)


# -- invalid and wrong pixels -----------------------------------------------------------------------


def test_left_border_band_is_as_wide_as_the_disparity_and_invalid():
    scene = SimScene(wall_at(0.5, height=1.0, half_width=3.0), floor=False, backdrop=False)
    z = depth(scene, DepthNoise.realistic())
    band = FX * 0.05 / 0.5  # 45 px at 0.5 m
    rows = slice(100, 380)
    assert (z[rows, :int(band) - 1] == 0).all()
    assert (z[rows, int(band) + 2:int(band) + 60] > 0).mean() > 0.9


def test_stereo_shadow_left_of_a_near_object_is_invalid_and_flying_pixels_lie_between():
    wall = wall_at(3.0)
    box = Solid("board", tuple(_box_faces(CAM_X + 1.0, 0.0, 0.2, 0.6, 1.0)))  # front face 1 m ahead, x = 0.9..1.1 m
    scene = SimScene(wall, [box], floor=False, backdrop=False)
    exact = render_depth_metres(scene, T_GC, K, CAM.width, CAM.height)
    z = depth(scene, DepthNoise.realistic(dropout=0.0, blobs=0.0), seed=2)
    fb = FX * 0.05
    near, far = 1.0, 3.0
    rows = range(200, 280)
    shadow = fb / near - fb / far  # px hidden from the right imager left of the box
    lefts, flying = [], []
    for r in rows:
        on_box = np.flatnonzero(np.isclose(exact[r], near, atol=1e-6))
        left, right = on_box.min(), on_box.max()
        lefts.append(z[r, left - int(shadow) + 1:left - 1])  # the shadow
        beyond = z[r, left - int(shadow) - 12:left - int(shadow) - 4]  # the wall left of the shadow
        assert (beyond > 0).mean() > 0.8
        # the right edge has no shadow: there the matcher's window mixes box and wall
        edge = z[r, right - 6:right + 8]
        between = edge[(edge > near + 0.1) & (edge < far - 0.3)]
        flying += list(between)
        cols = right - 6 + np.flatnonzero((edge > near + 0.1) & (edge < far - 0.3))
        assert np.all(np.abs(cols - right) <= 3)  # only along the edge
    assert np.mean([(s == 0).mean() for s in lefts]) > 0.97
    assert len(flying) > 30  # dozens of points between the surfaces, where a real camera puts them
    assert min(flying) > near and max(flying) < far


def _box_faces(x0, y, size_x, size_y, height):
    from drivers.sim.clutter import cuboid_faces

    return cuboid_faces((x0 + size_x / 2, y, height / 2 - 0.5), (size_x, size_y, height + 1.0))


def test_range_limits_and_fill_rate_beyond_4_m():
    fill = {}
    for z in (0.15, 3.0, 6.0, 9.0):
        scene = SimScene(wall_at(z, height=8.0, half_width=12.0, bottom=-8.0), floor=False, backdrop=False)
        fill[z] = float((depth(scene, replace(DepthNoise.realistic(), dropout=0.0, blobs=0.0))[:, 150:] > 0).mean())
    assert fill[0.15] == 0.0  # nearer than the minimum range
    assert fill[3.0] > 0.95
    assert 0.4 < fill[6.0] < 0.85
    assert fill[9.0] < 0.2


def test_blobs_and_dropouts_lose_about_the_stated_fraction():
    scene = SimScene(wall_at(1.0), floor=False, backdrop=False)
    no_holes = replace(DepthNoise.realistic(), blobs=0.0, dropout=0.0)
    base = np.mean([(depth(scene, no_holes, seed=s)[:, 100:] == 0).mean() for s in range(6)])
    lost = np.mean([(depth(scene, replace(no_holes, blobs=0.05, dropout=0.01), seed=s)[:, 100:] == 0).mean()
                    for s in range(6)])
    assert 0.035 < lost - base < 0.08


def test_same_seed_same_frame():
    pm = room_grid_map(2, 1, seed=3)
    scene = SimScene(pm, random_site_clutter(pm, np.random.default_rng(5), 6), walls=as_built(pm, np.random.default_rng(5)))
    pose = (2.2, 2.0, 0.3)
    a = render_depth_frame(ROBOT, scene, "front", pose, rng=np.random.default_rng(9))
    b = render_depth_frame(ROBOT, scene, "front", pose, rng=np.random.default_rng(9))
    c = render_depth_frame(ROBOT, scene, "front", pose, rng=np.random.default_rng(10))
    assert np.array_equal(a.depth, b.depth) and not np.array_equal(a.depth, c.depth)
    again = random_site_clutter(pm, np.random.default_rng(5), 6)
    first = random_site_clutter(pm, np.random.default_rng(5), 6)
    assert [s.kind for s in again] == [s.kind for s in first]
    assert all(np.array_equal(p, q) for s, t in zip(again, first) for p, q in zip(s.polygons, t.polygons))


# -- site clutter -----------------------------------------------------------------------------------


def _drawn_points(plane_map, item, pose=(0.0, 0.0, 0.0), camera="front"):
    """Ground-frame points of the pixels the item changes, and how many pixels see the map there."""
    cam = ROBOT.camera(camera)
    T = pose_to_T_ground_robot(*pose) @ cam.T_robot_camera
    Kc = cam.intrinsics_from_fov()
    before = [(p.id, [q.copy() for q in p.polygons]) for p in plane_map.planes]
    # No backdrop: around a lone test wall it would stand between the camera and the items.
    bare = render_depth_metres(SimScene(plane_map, backdrop=False), T, Kc, cam.width, cam.height)
    withit = render_depth_metres(SimScene(plane_map, [item], backdrop=False), T, Kc, cam.width, cam.height)
    # The builder left the map alone: the same planes, the same polygons.
    assert len(plane_map.planes) == len(before)
    for (pid, polys), p in zip(before, plane_map.planes):
        assert pid == p.id and all(np.array_equal(a, b) for a, b in zip(polys, p.polygons))
    changed = np.abs(withit - bare) > 1e-6
    pts, _, _ = points_G(np.where(changed, withit, 0.0), Kc, T)
    return pts


def _inside(pts, item, tol=0.02):  # edge pixels: within a pixel's footprint of the item
    lo, hi = item.bounds()
    return np.all((pts >= lo - tol) & (pts <= hi + tol), axis=1)


def test_person_and_pallet_and_shelving_are_drawn_where_they_stand():
    pm = wall_at(5.0)
    for item in (person(2.0, 0.3, yaw=1.0), pallet(2.5, -0.5, yaw=0.4, stack=3), shelving(3.0, 1.0, rng=np.random.default_rng(1))):
        pts = _drawn_points(pm, item)
        assert len(pts) > 2000, item.kind
        assert _inside(pts, item).all(), item.kind
    p = person(2.0, 0.0175, width=0.5, depth=0.3)
    pts = _drawn_points(pm, p)
    assert pts[:, 0].min() == pytest.approx(2.0 - 0.25, abs=0.01)  # its nearest side faces the camera
    lo, hi = p.bounds()
    assert hi[2] == pytest.approx(1.75) and hi[1] - lo[1] == pytest.approx(0.3, abs=0.01)
    stack = pallet(2.5, 0.0, stack=4)
    assert stack.bounds()[1][2] == pytest.approx(0.6)


def test_a_parallel_panel_sits_at_its_offset_over_its_share_of_the_wall():
    pm = wall_at(2.5, height=2.7, half_width=2.0)
    plane = pm["wall"]
    panel = parallel_panel(plane, 0.15, 0.6, np.random.default_rng(2))
    f = wall_frame(plane)
    assert panel.info["s1"] - panel.info["s0"] == pytest.approx(0.6 * f.length)
    pts = _drawn_points(pm, panel)
    dist = pts @ plane.normal + plane.d  # in front of the wall, along its normal
    face = np.abs(dist - 0.15) < 1e-4
    assert face.mean() > 0.9  # nearly everything the camera sees of it is its face, 0.15 m before the wall
    s = f.s_of(pts[face])
    assert s.min() >= panel.info["s0"] - 0.01 and s.max() <= panel.info["s1"] + 0.01  # an edge pixel's footprint
    with pytest.raises(ConfigError, match="coverage"):
        parallel_panel(plane, 0.15, 1.5)


def test_boards_lean_on_the_wall_at_their_angle():
    pm = wall_at(2.0, height=2.7, half_width=3.0)
    plane = pm["wall"]
    boards = leaning_boards(plane, 3.0, count=1, angle_deg=8.0, length=2.5)
    pts = _drawn_points(pm, boards)
    assert len(pts) > 2000 and _inside(pts, boards).all()
    dist = pts @ plane.normal + plane.d
    # The face seen from the camera: at height z it stands (L cos a - z) tan a + t / cos a from the wall.
    a, t = math.radians(8.0), 0.018
    L = 2.5
    expect = (L * math.cos(a) - pts[:, 2]) * math.tan(a) + t / math.cos(a)
    on_face = np.abs(dist - expect) < 2e-3
    assert on_face.mean() > 0.9
    assert dist.max() <= L * math.sin(a) + t + 0.01  # its foot (and edge pixels)


def test_a_door_leaf_opens_in_a_map_opening_at_its_angle():
    pm = room_grid_map(1, 2, seed=4)  # two rooms, one door between them
    openings = map_openings(pm)
    assert {o.plane_id for o in openings} == {"r0_0_n", "r0_1_s"}
    o = next(o for o in openings if o.plane_id == "r0_0_n")
    assert o.width == pytest.approx(0.9, abs=1e-6) and o.top == pytest.approx(2.1, abs=1e-6)
    leaf = door_leaf(o, 90.0, hinge="start")
    f = o.frame
    hinge = f.origin + o.s0 * f.along
    # a robot in the first room looking at the door from 1.5 m
    mid = f.origin + 0.5 * (o.s0 + o.s1) * f.along + 1.5 * f.normal
    heading = math.atan2(-f.normal[1], -f.normal[0])
    pts = _drawn_points(pm, leaf, pose=(mid[0] - 0.1 * math.cos(heading), mid[1] - 0.1 * math.sin(heading), heading))
    assert len(pts) > 500 and _inside(pts, leaf).all()
    # open 90 degrees: the leaf stands square to the wall, within its thickness of the hinge line
    across = (pts - hinge) @ f.along
    assert np.all((across > -0.01) & (across < 0.06))
    assert ((pts - hinge) @ f.normal).max() == pytest.approx(o.width - 0.01 + 0.005, abs=0.02)


def test_random_site_clutter_mixes_the_kinds_and_keeps_clear():
    pm = room_grid_map(2, 2, seed=1)
    keep = [(2.2, 2.2)]
    items = random_site_clutter(pm, np.random.default_rng(3), 15, keep_clear=keep, clearance=0.8)
    assert len(items) == 15
    assert len({s.kind for s in items}) >= 4 and {s.kind for s in items} <= set(SITE_KINDS)
    for s in items:
        lo, hi = s.bounds()
        q = np.clip(keep[0], lo[:2], hi[:2])
        assert math.hypot(*(q - np.array(keep[0]))) >= 0.8
    assert random_site_clutter(wall_at(1.0), np.random.default_rng(0), 3, kinds=("door",)) == []  # no openings
    with pytest.raises(ConfigError, match="unknown kind"):
        random_site_clutter(pm, np.random.default_rng(0), 2, kinds=("crane",))


# -- walls as built ---------------------------------------------------------------------------------


@pytest.mark.parametrize("dev", [WallDeviation(offset=0.015), WallDeviation(offset=-0.012),
                                 WallDeviation(bow=0.010), WallDeviation(tilt_deg=0.3),
                                 WallDeviation(offset=0.005, bow=-0.008, tilt_deg=-0.3)])
def test_as_built_walls_move_the_rendered_wall_by_the_stated_amount(dev):
    x = CAM_X + 1.8
    plane = make_plane("wall", [[[x, 2.0, 0.0], [x, -2.0, 0.0], [x, -2.0, 2.7], [x, 2.0, 2.7]]])  # 4 m long
    pm = PlaneMap([plane])
    walls = built_walls(pm, {"wall": dev})
    z = render_depth_metres(SimScene(pm, walls=walls, floor=False, backdrop=False), T_GC, K, CAM.width, CAM.height)
    pts, _, _ = points_G(z)
    moved = pts @ plane.normal + plane.d  # + towards the camera
    expect = np.array([walls.displacement("wall", p) for p in pts[::97]])
    assert np.abs(moved[::97] - expect).max() < 3e-4  # the strips' chords: 0.16 mm off a 10 mm bow
    assert np.ptp(expect) + abs(expect).max() > 0.004  # and the deviation is really there
    if dev.bow:
        f = wall_frame(plane)
        mid = (np.abs(f.s_of(pts) - 0.5 * (f.s_min + f.s_max)) < 0.05) & (np.abs(pts[:, 2] - 0.5) < 0.02)
        assert np.median(moved[mid]) == pytest.approx(dev.offset + dev.bow + 0.5 * math.tan(math.radians(dev.tilt_deg)),
                                                       abs=3e-4)
    assert plane.d == pm["wall"].d  # the map keeps the wall where it was drawn


def test_as_built_samples_stay_within_the_stated_bounds_and_repeat_per_seed():
    pm = room_grid_map(2, 2, seed=0)
    a = as_built(pm, np.random.default_rng(11), offset_std=0.01, bow_max=0.01, tilt_deg=0.3)
    b = as_built(pm, np.random.default_rng(11), offset_std=0.01, bow_max=0.01, tilt_deg=0.3)
    offs = np.array([d.offset for d in a.deviations.values()])
    assert np.abs(offs).max() <= 0.025 and offs.std() == pytest.approx(0.01, rel=0.35)
    assert max(abs(d.bow) for d in a.deviations.values()) <= 0.01
    assert max(abs(d.tilt_deg) for d in a.deviations.values()) <= 0.3
    assert a.deviations == b.deviations and all(np.array_equal(p, q) for p, q in zip(a.polygons, b.polygons))
    # a wall moved back from a corner still meets its neighbour: no slit to the backdrop
    cam = ROBOT.camera("front")
    Kc = cam.intrinsics_from_fov()
    T = pose_to_T_ground_robot(1.2, 1.2, math.radians(225)) @ cam.T_robot_camera  # looking into the room's corner
    back = built_walls(pm, {"r0_0_s": WallDeviation(offset=-0.02), "r0_0_w": WallDeviation(offset=-0.02)})
    z = render_depth_metres(SimScene(pm, walls=back), T, Kc, cam.width, cam.height)
    assert z[: cam.height // 2].max() < 2.5  # nothing of the backdrop, 3 m beyond the walls


# -- command line -----------------------------------------------------------------------------------


def test_render_command_models_scale_error_and_site(tmp_path, capsys):
    common = ["render", "--robot", "config/robot.yaml", "--map", "config/maps/paper_arena.yaml",
              "--pose", "0.5", "0.5", str(math.pi), "--camera", "front", "--seed", "3"]
    paths = {}
    for name, extra in (("plain", []), ("long", ["--depth-scale-error", "0.01"]), ("simple", ["--noise", "simple"]),
                        ("site", ["--site", "3", "--as-built"])):
        paths[name] = tmp_path / f"{name}.npz"
        assert main(common + ["--out", str(paths[name])] + extra) == 0
    plain, long = (load_snapshot(paths[k]).depth.astype(float) for k in ("plain", "long"))
    both = (plain > 0) & (long > 0)
    assert np.median(long[both] / plain[both]) == pytest.approx(1.01, abs=0.002)
    assert not np.array_equal(load_snapshot(paths["simple"]).depth, load_snapshot(paths["plain"]).depth)
    capsys.readouterr()
    assert exit_status(common + ["--out", str(tmp_path / "x.npz"), "--depth-scale-error", "0.5"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--depth-scale-error" in err[0]


def exit_status(argv) -> int:
    """``robotctl`` exit status: usage errors leave argparse by SystemExit, bad values by main's return."""
    try:
        return main(argv)
    except SystemExit as e:
        return int(e.code)


def test_sim_command_refuses_a_bad_scale_error_in_one_line(capsys):
    base = ["sim", "--path", "config/paths/paper_4_3.yaml", "--runs", "1", "--no-plots"]
    for bad, word in (("rear=0.01", "rear"), ("lots", "lots"), ("front=0.3", "front")):
        assert exit_status(base + ["--depth-scale-error", bad]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and word in err[0] and "Traceback" not in err[0]



def test_a_world_with_site_items_and_walls_as_built_keeps_its_seeds_wheels_and_boxes():
    from drivers.sim.render import Box
    from drivers.sim.world import WorldSettings, sample_world

    pm = room_grid_map(2, 2, seed=1)
    start = (2.2, 2.2, 0.0)
    plain_wheels, plain = sample_world(pm, start, 7, 0.01, 3)
    wheels, site = sample_world(pm, start, 7, 0.01, 3, site=8, as_built=True)
    assert wheels == plain_wheels
    assert [c for c in site.clutter if isinstance(c, Box)] == list(plain.clutter)
    assert len([c for c in site.clutter if isinstance(c, Solid)]) == 8 and site.walls is not None
    assert WorldSettings().depth_noise == DepthNoise.realistic()  # the simulator's default camera
