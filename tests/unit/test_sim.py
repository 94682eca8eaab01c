"""The robot simulator: kinematics against closed forms, rendering against a pinhole model written
out here, scenarios against their formulas, and determinism."""

from __future__ import annotations

import math
import time

import cv2
import numpy as np
import pytest

from vistrack.services.camera.scenarios import (
    BUILTIN_SCENARIOS,
    ScenarioError,
    load_scenario,
    parse_scenario,
)
from vistrack.services.camera.sim import (
    Camera,
    Command,
    Robot,
    RobotLimits,
    Simulator,
    TextureError,
    load_texture,
)

# -- helpers -----------------------------------------------------------------------------------


def scene(distance=2.0, lateral=0.0, size=1.0, duration=10.0, extra=""):
    """A scenario whose target sits at (distance, lateral) from t = 0 on."""
    return parse_scenario(f"""
name: fixed
duration_s: {duration}
target_size_m: {size}
components:
  - {{type: step, axis: distance, at_s: 0, offset_m: {distance - 2.0}}}
  - {{type: step, axis: lateral, at_s: 0, offset_m: {lateral}}}
{extra}""")


def blob_texture(w, h, centre, sigma, base=100.0, amp=120.0):
    """(h, w) uint8: uniform ``base`` with a Gaussian blob of peak ``amp`` at texture px
    ``centre`` = (column, row)."""
    a, b = np.meshgrid(np.arange(w), np.arange(h))
    g = amp * np.exp(-((a - centre[0]) ** 2 + (b - centre[1]) ** 2) / (2 * sigma**2))
    return np.clip(np.rint(base + g), 0, 255).astype(np.uint8)


def pinhole(point, robot, width, height, f):
    """u, v of world ``point`` seen from robot pose (x, y, theta): K [R | t] X written out.

    World: x forward, y left, z up. Camera (OpenCV): X right = -y_robot, Y down = -z, Z forward
    = x_robot. Principal point at the centre of the pixel grid, pixel centres at integers.
    """
    x, y, theta = robot
    c, s = math.cos(theta), math.sin(theta)
    r_wr = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])  # robot -> world
    r_cr = np.array([[0, -1, 0], [0, 0, -1], [1, 0, 0]])  # robot -> camera axes
    r = r_cr @ r_wr.T
    t = -r @ np.array([x, y, 0.0])
    k = np.array([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1]])
    p = k @ (r @ np.asarray(point, float) + t)
    return p[0] / p[2], p[1] / p[2]


def texture_point(tex_px, tex_shape, centre, width_m):
    """World point of texture pixel (a, b) on a plane facing the robot (documented mapping):
    columns go to world -y, rows to world -z, the texture's centre at ``centre`` (x, y, 0)."""
    h, w = tex_shape
    m = width_m / w
    a, b = tex_px
    return np.array([centre[0], centre[1] - (a - (w - 1) / 2) * m, -(b - (h - 1) / 2) * m])


def blob_centroid(frame, near, base, radius=14):
    """Intensity-weighted centroid (u, v) of the bright blob around ``near``, above ``base``."""
    img = frame.astype(float) - base
    u0, v0 = (int(round(c)) for c in near)
    win = img[v0 - radius:v0 + radius + 1, u0 - radius:u0 + radius + 1]
    # re-centre on the peak so a wrong prediction cannot bias the window
    pv, pu = np.unravel_index(np.argmax(win), win.shape)
    u0, v0 = u0 - radius + pu, v0 - radius + pv
    win = np.clip(img[v0 - radius:v0 + radius + 1, u0 - radius:u0 + radius + 1], 0, None)
    vv, uu = np.mgrid[v0 - radius:v0 + radius + 1, u0 - radius:u0 + radius + 1]
    total = win.sum()
    cu, cv = (win * uu).sum() / total, (win * vv).sum() / total
    var = (win * ((uu - cu) ** 2 + (vv - cv) ** 2)).sum() / total / 2
    return cu, cv, var


# -- robot kinematics --------------------------------------------------------------------------

LIMITS = RobotLimits(max_speed=1.0, max_accel=0.8, max_yaw_rate=1.2, max_yaw_accel=2.0)


@pytest.mark.parametrize(("axis", "cmd", "accel"), [
    ("vx", 0.5, 0.8), ("vy", -0.6, 0.8), ("wz", 0.9, 2.0), ("wz", -0.4, 2.0)])
@pytest.mark.parametrize("dt", [0.01, 1 / 30])
def test_velocity_step_response_follows_acceleration_limit(axis, cmd, accel, dt):
    robot = Robot(LIMITS)
    i = ("vx", "vy", "wz").index(axis)
    for n in range(1, int(2.0 / dt)):
        robot.step(Command(**{axis: cmd}), dt)
        expected = math.copysign(min(accel * n * dt, abs(cmd)), cmd)
        assert robot.velocity[i] == pytest.approx(expected, abs=1e-9), f"step {n}"
        others = [v for j, v in enumerate(robot.velocity) if j != i]
        assert others == [0.0, 0.0]


@pytest.mark.parametrize(("axis", "cmd", "limit", "accel"), [
    ("vx", 3.0, 1.0, 0.8), ("vy", -2.0, 1.0, 0.8), ("wz", 5.0, 1.2, 2.0)])
def test_velocity_saturates_at_the_velocity_limit(axis, cmd, limit, accel):
    robot = Robot(LIMITS)
    i = ("vx", "vy", "wz").index(axis)
    dt = 0.01
    history = []
    for _ in range(300):
        robot.step({axis: cmd, "stale": False}, dt)
        history.append(robot.velocity[i])
    t = dt * np.arange(1, 301)
    expected = np.sign(cmd) * np.minimum(accel * t, limit)
    np.testing.assert_allclose(history, expected, atol=1e-9)
    assert abs(history[-1]) == pytest.approx(limit)


def test_diagonal_speed_is_limited_on_the_norm_keeping_the_direction():
    robot = Robot(RobotLimits(max_speed=0.5, max_accel=10.0))
    for _ in range(100):
        robot.step(Command(vx=2.0, vy=1.0), 0.05)
    vx, vy, _ = robot.velocity
    assert math.hypot(vx, vy) == pytest.approx(0.5)
    assert vy / vx == pytest.approx(0.5)


def test_deceleration_and_position_follow_the_trapezoid():
    a, v, dt = 0.8, 0.5, 0.005
    robot = Robot(LIMITS)
    n_up = 400  # 2 s: ramp to 0.5 m/s in 0.625 s, then cruise
    for _ in range(n_up):
        robot.step(Command(vx=v), dt)
    t_up = n_up * dt
    x_expected = v * v / (2 * a) + v * (t_up - v / a)
    assert robot.x == pytest.approx(x_expected, abs=1e-9)
    for n in range(1, 200):
        robot.step(Command(), dt)
        assert robot.vx == pytest.approx(max(v - a * n * dt, 0.0), abs=1e-9)
    x_expected += v * v / (2 * a)  # braking distance
    assert robot.x == pytest.approx(x_expected, abs=1e-9)
    assert robot.y == 0.0 and robot.theta == 0.0


@pytest.mark.parametrize(("theta", "cmd", "direction"), [
    (math.pi / 2, Command(vx=0.4), (0.0, 1.0)),     # facing world +y, forward is +y
    (math.pi / 2, Command(vy=0.4), (-1.0, 0.0)),    # robot left is world -x
    (-math.pi / 4, Command(vx=0.4), (math.sqrt(0.5), -math.sqrt(0.5))),
])
def test_commands_are_in_the_robot_frame(theta, cmd, direction):
    robot = Robot(RobotLimits(max_accel=100.0), theta=theta)
    for _ in range(50):
        robot.step(cmd, 0.02)
    dist = math.hypot(robot.x, robot.y)
    assert dist > 0.3
    assert robot.x / dist == pytest.approx(direction[0], abs=1e-9)
    assert robot.y / dist == pytest.approx(direction[1], abs=1e-9)
    assert robot.theta == pytest.approx(theta)


def test_constant_twist_stays_on_one_circle_at_a_coarse_time_step():
    # Euler integration at dt = 0.2 s drifts outwards; the SE(2) exponential must not
    v, w, dt = 0.6, 0.8, 0.2
    robot = Robot(RobotLimits(max_accel=100.0, max_yaw_accel=100.0))
    robot.step(Command(vx=v, wz=w), dt)  # reaches the command within the first step
    centres = []
    for _ in range(40):
        robot.step(Command(vx=v, wz=w), dt)
        x, y, th = robot.pose
        centres.append((x - v / w * math.sin(th), y + v / w * math.cos(th)))
    np.testing.assert_allclose(centres, np.repeat([centres[0]], len(centres), 0), atol=1e-9)


@pytest.mark.parametrize(("field", "value"), [
    ("max_speed", 0.0), ("max_speed", -1.0), ("max_accel", float("nan")),
    ("max_yaw_rate", 1e6), ("max_yaw_accel", "2"), ("max_accel", True)])
def test_robot_limits_errors_name_field_value_and_range(field, value):
    with pytest.raises(ValueError) as err:
        RobotLimits(**{field: value})
    text = str(err.value)
    assert field in text and repr(value) in text and "(0, " in text


@pytest.mark.parametrize("bad", [{"vx": float("inf")}, {"wz": "fast"}, {"vy": None}])
def test_bad_commands_are_rejected(bad):
    with pytest.raises(ValueError, match=next(iter(bad))):
        Robot().step(bad, 0.1)


def test_negative_dt_is_rejected():
    with pytest.raises(ValueError, match="dt"):
        Robot().step(Command(), -0.1)


# -- camera ------------------------------------------------------------------------------------

def test_default_camera_is_256_square_with_60_degree_fov():
    cam = Camera()
    assert (cam.width, cam.height) == (256, 256)
    # independent: half-width over focal length is tan(30 deg)
    assert 128 / cam.focal_px == pytest.approx(math.tan(math.radians(30)))
    assert Camera(width=512).focal_px == pytest.approx(2 * cam.focal_px)


@pytest.mark.parametrize(("field", "value"), [
    ("width", 8), ("height", 100.5), ("focal_px", 0.0), ("noise_sigma", -1.0),
    ("blur_sigma", 50.0)])
def test_camera_errors_name_field_and_value(field, value):
    with pytest.raises(ValueError) as err:
        Camera(**{field: value})
    assert f"Camera.{field}={value!r}" in str(err.value)


# -- rendering geometry ------------------------------------------------------------------------

TEX_SHAPE = (512, 512)
BLOB = (150.0, 350.0)  # off-centre in both axes, so a flipped axis cannot pass


@pytest.mark.parametrize("camera", [Camera(), Camera(width=320, height=240, focal_px=300.0)])
@pytest.mark.parametrize(("robot", "target"), [
    ((0.0, 0.0, 0.0), (2.0, 0.0)),
    ((0.3, -0.2, 0.0), (2.0, 0.1)),
    ((0.0, 0.0, 0.2), (2.0, 0.35)),
    ((0.5, 0.3, -0.15), (1.7, 0.0)),
    ((-0.4, 0.1, 0.1), (2.6, 0.4)),
    ((0.8, 0.0, 0.0), (2.0, 0.0)),  # 1.2 m: another pair of mip levels
])
def test_rendered_target_blob_lands_where_the_pinhole_model_puts_it(camera, robot, target):
    tex = blob_texture(TEX_SHAPE[1], TEX_SHAPE[0], BLOB, sigma=10.0)
    bg = np.full((64, 64), 20, np.uint8)
    sim = Simulator(scene(*target), camera=camera, texture=tex, background=bg)
    sim.reset(x=robot[0], y=robot[1], theta=robot[2])
    frame = sim.render()
    point = texture_point(BLOB, TEX_SHAPE, (target[0], target[1]), 1.0)
    expected = pinhole(point, robot, camera.width, camera.height, camera.focal_px)
    assert 10 < expected[0] < camera.width - 10 and 10 < expected[1] < camera.height - 10
    u, v, _ = blob_centroid(frame, expected, base=100.0)
    assert math.hypot(u - expected[0], v - expected[1]) < 0.25, (u, v, expected)
    # the simulator's own projection agrees with the model written out here
    np.testing.assert_allclose(sim.project(point), expected, atol=1e-9)


@pytest.mark.parametrize("robot", [(0.0, 0.0, 0.0), (0.7, -0.5, 0.25), (-0.3, 0.4, -0.3)])
def test_rendered_background_blob_lands_where_the_pinhole_model_puts_it(robot):
    shape, blob = (1024, 1024), (560.0, 470.0)
    bg = blob_texture(shape[1], shape[0], blob, sigma=5.0, base=60.0, amp=150.0)
    tex = np.full((32, 32), 60, np.uint8)
    # the target steps far to the side, out of view
    sim = Simulator(scene(2.0, -5.0), texture=tex, background=bg)
    sim.reset(x=robot[0], y=robot[1], theta=robot[2])
    frame = sim.render()
    point = texture_point(blob, shape, (6.0, 0.0), 16.0)
    expected = pinhole(point, robot, 256, 256, Camera().focal_px)
    u, v, _ = blob_centroid(frame, expected, base=60.0)
    assert math.hypot(u - expected[0], v - expected[1]) < 0.25, (u, v, expected)


def test_target_occludes_the_background_and_has_its_projected_extent():
    sim = Simulator(scene(2.0, 0.0), texture=np.full((64, 64), 200, np.uint8),
                    background=np.full((64, 64), 40, np.uint8))
    frame = sim.render()
    # the 1 m target at 2 m spans f * 1 / 2 px, centred
    half = Camera().focal_px * 0.5 / 2.0
    row = frame[128].astype(float)
    covered = (row - 40) / (200 - 40)  # fractional coverage, anti-aliased edges included
    assert covered.sum() == pytest.approx(2 * half, abs=0.5)
    assert frame[128, 128] == 200 and frame[5, 5] == 40


def test_ground_truth_centre_and_scale_match_the_pinhole_model():
    sim = Simulator(scene(1.5, 0.2))
    robot = (0.2, -0.1, 0.1)
    sim.reset(x=robot[0], y=robot[1], theta=robot[2])
    u, v = sim.target_center_px()
    assert (u, v) == pytest.approx(pinhole((1.5, 0.2, 0.0), robot, 256, 256, Camera().focal_px))
    # depth along the optical axis of the target centre, reference distance 2 m
    depth = math.cos(robot[2]) * (1.5 - robot[0]) + math.sin(robot[2]) * (0.2 - robot[1])
    assert sim.target_scale() == pytest.approx(2.0 / depth)
    truth = sim.truth()
    assert {k: truth[k] for k in ("x", "y", "theta", "tx", "ty")} == pytest.approx(
        {"x": 0.2, "y": -0.1, "theta": 0.1, "tx": 1.5, "ty": 0.2})


def test_project_many_points_and_points_behind_give_nan():
    sim = Simulator(scene())
    pts = np.array([[2.0, 0.3, -0.1], [4.0, -1.0, 0.5], [-1.0, 0.0, 0.0]])
    uv = sim.project(pts)
    assert uv.shape == (3, 2)
    for p, got in zip(pts[:2], uv[:2], strict=True):
        assert got == pytest.approx(pinhole(p, (0, 0, 0), 256, 256, Camera().focal_px))
    assert np.isnan(uv[2]).all()
    with pytest.raises(ValueError, match="shape"):
        sim.project([1.0, 2.0])


def test_columns_beyond_the_background_horizon_are_void_not_mirrored():
    sim = Simulator(scene(2.0, -5.0))
    theta = 1.2
    sim.reset(theta=theta)
    frame = sim.render()
    f = Camera().focal_px
    # a ray through column u heads away from the wall when cos(theta) + sin(theta)(u-cx)/f <= 0
    horizon = 127.5 - f / math.tan(theta)
    assert (frame[:, :int(horizon) - 1] == 128).all()
    assert frame[:, int(horizon) + 3:].std() > 5


def test_lighting_gain_and_offset_follow_the_scenario():
    extra = "  - {type: lighting, period_s: 4, gain_amplitude: 0.2, offset_amplitude: 10}"
    sim = Simulator(scene(extra=extra), texture=np.full((16, 16), 100, np.uint8),
                    background=np.full((16, 16), 100, np.uint8))
    for t, s in ((0.0, 0.0), (1.0, 1.0), (3.0, -1.0), (0.5, math.sqrt(0.5))):
        sim.reset()
        sim.step(Command(), t)
        expected = (1 + 0.2 * s) * 100 + 10 * s
        assert np.abs(sim.render().astype(float) - expected).max() <= 0.5 + 1e-9


def test_noise_has_the_configured_sigma():
    sim = Simulator(scene(), camera=Camera(noise_sigma=4.0), texture=np.full((16, 16), 128,
                                                                             np.uint8),
                    background=np.full((16, 16), 128, np.uint8))
    frame = sim.render().astype(float)
    assert frame.mean() == pytest.approx(128, abs=0.1)
    assert frame.std() == pytest.approx(4.0, rel=0.03)


def test_blur_adds_its_variance_to_a_blob():
    # Gaussians convolve by adding variances: a blob of variance s^2 blurred by sigma_b has
    # s^2 + sigma_b^2
    tex = blob_texture(512, 512, BLOB, sigma=12.0)
    target = (2.0, 0.0)
    point = texture_point(BLOB, TEX_SHAPE, target, 1.0)
    expected = pinhole(point, (0, 0, 0), 256, 256, Camera().focal_px)
    variances = []
    for blur in (0.0, 2.0):
        sim = Simulator(scene(*target), camera=Camera(blur_sigma=blur), texture=tex,
                        background=np.full((16, 16), 100, np.uint8))
        variances.append(blob_centroid(sim.render(), expected, base=100.0)[2])
    assert variances[1] - variances[0] == pytest.approx(4.0, rel=0.1)


# -- determinism -------------------------------------------------------------------------------

def run(seed, n=5, camera=None):
    sim = Simulator("default", camera=camera or Camera(noise_sigma=3.0, blur_sigma=0.7),
                    seed=seed)
    frames = []
    for _ in range(n):
        sim.step(Command(vx=0.1, vy=-0.05, wz=0.02), 1 / 30)
        frames.append(sim.render())
    return frames, sim


def test_same_seed_gives_identical_frames():
    a, sim = run(3)
    b, _ = run(3)
    for fa, fb in zip(a, b, strict=True):
        assert fa.dtype == np.uint8 and fa.shape == (256, 256)
        np.testing.assert_array_equal(fa, fb)
    sim.reset()
    c = []
    for _ in range(5):
        sim.step(Command(vx=0.1, vy=-0.05, wz=0.02), 1 / 30)
        c.append(sim.render())
    np.testing.assert_array_equal(np.stack(a), np.stack(c))  # reset replays the run


def test_different_seeds_give_different_noise():
    a, _ = run(3, n=1)
    b, _ = run(4, n=1)
    assert not np.array_equal(a[0], b[0])


# -- textures ----------------------------------------------------------------------------------

def test_texture_file_in_colour_is_converted_to_grey(tmp_path):
    bgr = np.zeros((40, 60, 3), np.uint8)
    bgr[:] = (200, 50, 10)
    path = tmp_path / "target.png"
    assert cv2.imwrite(str(path), bgr)
    grey = load_texture(path)
    expected = 0.114 * 200 + 0.587 * 50 + 0.299 * 10  # ITU-R BT.601 luma
    assert grey.shape == (40, 60) and grey.dtype == np.uint8
    assert np.abs(grey.astype(float) - expected).max() <= 1.0
    sim = Simulator(scene(), texture=str(path))
    assert abs(float(sim.render()[128, 128]) - expected) <= 1.0


def test_missing_or_unreadable_texture_files_give_clear_errors(tmp_path):
    missing = tmp_path / "nope.png"
    with pytest.raises(TextureError, match="nope.png: no such file"):
        load_texture(missing)
    junk = tmp_path / "junk.png"
    junk.write_text("not an image")
    with pytest.raises(TextureError, match="junk.png: not an image"):
        Simulator(scene(), texture=junk)
    with pytest.raises(TextureError, match="folder"):
        load_texture(tmp_path)
    with pytest.raises(TextureError, match="too small"):
        Simulator(scene(), texture=np.zeros((4, 4), np.uint8))


# -- scenarios ---------------------------------------------------------------------------------

def test_sine_component_gives_the_specified_positions():
    s = parse_scenario("""
name: s
duration_s: 12
components:
  - {type: sine, axis: lateral, amplitude_m: 0.3, period_s: 6, phase_deg: 30, start_s: 1,
     end_s: 10}
""")
    for t in (0.0, 0.99, 1.0, 2.5, 4.0, 7.3, 9.99, 10.0, 11.0):
        want = 0.3 * math.sin(2 * math.pi * (t - 1) / 6 + math.pi / 6) if 1 <= t < 10 else 0.0
        assert s.target_position(t) == pytest.approx((2.0, want), abs=1e-12)


def test_step_components_add_up():
    s = parse_scenario("""
name: steps
duration_s: 10
distance_m: 3
components:
  - {type: step, axis: lateral, at_s: 2, offset_m: 0.2}
  - {type: step, axis: lateral, at_s: 5, offset_m: -0.5}
  - {type: step, axis: distance, at_s: 4, offset_m: -1}
""")
    table = {0.0: (3.0, 0.0), 1.99: (3.0, 0.0), 2.0: (3.0, 0.2), 4.5: (2.0, 0.2),
             5.0: (2.0, -0.3), 9.0: (2.0, -0.3)}
    for t, want in table.items():
        assert s.target_position(t) == pytest.approx(want), t


def test_approach_profile_and_ramp_give_the_specified_distances():
    s = parse_scenario("""
name: a
duration_s: 20
components:
  - {type: profile, axis: distance, points: [[2, 0], [6, -0.8], [8, -0.8], [12, 0]]}
  - {type: ramp, axis: lateral, start_s: 1, end_s: 3, delta_m: 0.4}
""")
    table = {0: (2.0, 0.0), 2: (2.0, 0.2), 4: (1.6, 0.4), 6: (1.2, 0.4), 7: (1.2, 0.4),
             9: (1.4, 0.4), 12: (2.0, 0.4), 15: (2.0, 0.4)}
    for t, want in table.items():
        assert s.target_position(t) == pytest.approx(want), t


def test_simulator_follows_the_scenario_clock():
    sim = Simulator(parse_scenario("""
name: a
duration_s: 2
components:
  - {type: ramp, axis: distance, start_s: 0, end_s: 2, delta_m: -1}
"""))
    for _ in range(30):
        sim.step(Command(), 1 / 30)
    assert sim.pose()["tx"] == pytest.approx(1.5)
    assert not sim.done
    for _ in range(30):
        sim.step(Command(), 1 / 30)
    assert sim.done and sim.pose()["tx"] == pytest.approx(1.0)


@pytest.mark.parametrize(("duration", "fps", "frames"), [(0.5, 30, 15), (20, 7, 140),
                                                          (20, 30, 600), (0.1, 1000, 100)])
def test_a_scenario_lasts_its_frames_whatever_the_rounding(duration, fps, frames):
    """The clock sums steps in floating point: 15 steps of 1/30 s fell short of 0.5 s."""
    sim = Simulator(parse_scenario(f"name: a\nduration_s: {duration}\ncomponents: []\n"))
    steps = 0
    while not sim.done:
        sim.step(Command(), 1 / fps)
        steps += 1
    assert steps == frames


def test_builtin_scenarios_load():
    assert {"default", "sideways", "approach", "steps"} <= set(BUILTIN_SCENARIOS)
    for name in BUILTIN_SCENARIOS:
        assert load_scenario(name).name == name
    default = load_scenario("default")
    assert 15 <= default.duration_s <= 25
    t = np.linspace(0, default.duration_s, 2001)
    dist, lat = default.offsets(t)
    assert lat.max() > 0.1 and lat.min() < -0.1  # sideways
    assert dist.min() < -0.3 and dist[-1] == pytest.approx(0.0)  # approach and recede


def test_scenario_files_load_by_path(tmp_path):
    path = tmp_path / "mine.yaml"
    path.write_text("name: mine\nduration_s: 3\ncomponents:\n"
                    "  - {type: step, axis: lateral, at_s: 1, offset_m: 0.1}\n")
    s = load_scenario(path)
    assert s.name == "mine" and s.target_position(2.0) == pytest.approx((2.0, 0.1))
    sim = Simulator(str(path))
    assert sim.scenario == s


def test_unknown_scenario_name_lists_the_builtins():
    with pytest.raises(ScenarioError) as err:
        load_scenario("sidewayz")
    assert "sidewayz" in str(err.value)
    for name in ("default", "sideways", "approach", "steps"):
        assert name in str(err.value)


@pytest.mark.parametrize(("text", "line"), [
    ("name: x\nduration_s: 5: 6\ncomponents: []\n", 2),
    ("name: x\nduration_s: 5\ncomponents:\n  - {type: sine, axis: lateral\n  - {type: step}\n",
     5),
    ("name: x\nduration_s: 5\ncomponents:\n\t- type: sine\n", 4),
])
def test_malformed_yaml_reports_the_line(text, line):
    with pytest.raises(ScenarioError, match=f"mine.yaml: malformed YAML: line {line}, column"):
        parse_scenario(text, source="mine.yaml")


def test_unknown_component_type_names_the_key_and_the_allowed_types():
    text = ("name: x\nduration_s: 5\ncomponents:\n"
            "  - {type: step, axis: lateral, at_s: 1, offset_m: 0.1}\n"
            "  - {type: zigzag, axis: lateral}\n")
    with pytest.raises(ScenarioError) as err:
        parse_scenario(text)
    msg = str(err.value)
    assert "components[1].type" in msg and "'zigzag'" in msg
    for kind in ("sine", "step", "ramp", "profile", "lighting"):
        assert kind in msg


BASE = "name: x\nduration_s: 5\ncomponents:\n  - "


@pytest.mark.parametrize(("text", "fragments"), [
    (BASE + "{type: sine, axis: lateral, amplitude: 0.3, period_s: 2}",
     ["components[0].amplitude", "unknown key", "amplitude_m"]),
    (BASE + "{type: sine, axis: lateral, period_s: 2}",
     ["components[0].amplitude_m", "missing"]),
    (BASE + "{type: sine, axis: vertical, amplitude_m: 0.1, period_s: 2}",
     ["components[0].axis", "'vertical'", "lateral, distance"]),
    (BASE + "{type: sine, axis: lateral, amplitude_m: 0.1, period_s: 0}",
     ["components[0].period_s", "0.0", "out of range", "[0.01, 86400]"]),
    (BASE + "{type: sine, axis: lateral, amplitude_m: 0.1, period_s: 5.0e-324}",
     ["components[0].period_s", "5e-324", "out of range"]),
    (BASE + "{type: lighting, period_s: 1.0e-12}",
     ["components[0].period_s", "out of range"]),
    (BASE + "{type: step, axis: lateral, at_s: yes, offset_m: 0.1}",
     ["components[0].at_s", "True", "not a number"]),
    (BASE + "{type: ramp, axis: lateral, start_s: 3, end_s: 2, delta_m: 0.1}",
     ["components[0].end_s", "greater than start_s"]),
    (BASE + "{type: profile, axis: distance, points: [[0, 0], [2, -0.5], [2, 0]]}",
     ["components[0].points[2][0]", "greater than the previous"]),
    (BASE + "{type: ramp, axis: distance, start_s: 0, end_s: 4, delta_m: -1.9}",
     ["target distance reaches", "[0.3, 5.9]"]),
    (BASE + "sine", ["components[0]", "not a mapping"]),
    ("name: x\nduration_s: -1\n", ["duration_s", "-1.0", "out of range"]),
    ("name: x\n", ["duration_s", "missing"]),
    ("name: x\nduration_s: 5\nspeed: 2\n", ["speed", "unknown key", "components"]),
    ("- 1\n- 2\n", ["must be a mapping"]),
    ("name: x\nduration_s: 5\ndistance_m: 3\nbackground_distance_m: 3\n",
     ["background_distance_m", "must exceed"]),
])
def test_invalid_scenarios_name_the_problem(text, fragments):
    with pytest.raises(ScenarioError) as err:
        parse_scenario(text, source="s.yaml")
    msg = str(err.value)
    assert msg.startswith("s.yaml: ")
    for fragment in fragments:
        assert fragment in msg, msg


# -- speed -------------------------------------------------------------------------------------

@pytest.mark.bench
def test_render_time_is_well_under_5_ms():
    sim = Simulator("lighting", camera=Camera(noise_sigma=3.0, blur_sigma=0.7))
    times = []
    for _ in range(300):
        sim.step(Command(vy=0.05), 1 / 30)
        t0 = time.perf_counter()
        sim.render()
        times.append(time.perf_counter() - t0)
    median_ms = 1e3 * float(np.median(times))
    print(f"render: median {median_ms:.3f} ms, p99 {1e3 * np.percentile(times, 99):.3f} ms")
    assert median_ms < 2.5
