"""Tests of the simulator: truth, commands, effects, scene, lidar, bag and CSV output."""

from __future__ import annotations

import csv
import math
from pathlib import Path
import time

import numpy as np
import pytest
from rosbags.rosbag2 import Reader
from rosbags.typesys import get_typestore, Stores

from skidkin_ros.adapters.sim_writer import write_bag
from skidkin_ros.core.odometry.integrator import rollout
from skidkin_ros.errors import ParameterError
from skidkin_ros.sim import (EFFECT_NAMES, EFFECTS, LidarConfig, make_effect, random_effect,
                             SimConfig, simulate)
from skidkin_ros.sim.effects import EffectInput
from skidkin_ros.sim.robot import COMMAND_KINDS
from skidkin_ros.sim.scene import (Box, Cylinder, default_scene, Field, make_scene,
                                   outdoor_scene, Room, Scene)

# A scripted drive through the interesting parts of the input space (rad/s): forward, backward,
# an arc where one side turns twice the other, a spin.
SCRIPT = ((2.0, 4.0, 4.0), (2.0, -4.0, -4.0), (2.0, 2.0, 4.0), (2.0, -4.0, 4.0))


def scripted(**kwargs) -> SimConfig:
    options = {'duration_s': 9.0, 'seed': 5, 'script': SCRIPT, 'encoder_noise_rad_s': 0.0}
    options.update(kwargs)
    return SimConfig(**options)


@pytest.fixture(scope='module')
def baseline():
    return simulate(scripted())


def test_same_seed_same_drive_and_other_seed_differs():
    first = simulate(SimConfig(duration_s=20.0, seed=11))
    again = simulate(SimConfig(duration_s=20.0, seed=11))
    other = simulate(SimConfig(duration_s=20.0, seed=12))
    assert np.array_equal(first.trace.poses, again.trace.poses)
    assert np.array_equal(first.wheels.omega_l, again.wheels.omega_l)
    assert not np.array_equal(first.wheels.omega_l, other.wheels.omega_l)


def test_truth_is_the_true_model_integrated_on_the_fine_grid(baseline):
    model = baseline.config.bound_model()
    trace = baseline.trace
    twist = model.twist(trace.omega_l, trace.omega_r)
    dt_s = np.full(trace.t_ns.size, 1e-3)
    poses = rollout(twist, dt_s)[:-1]
    assert np.allclose(trace.twist, twist)
    assert np.allclose(trace.poses, poses, atol=1e-12)
    # the samples carry the truth at their stamps and the actual speeds at the wheel rate
    assert np.allclose(baseline.truth.poses, baseline.pose_at(baseline.wheels.t_ns))
    assert np.diff(baseline.wheels.t_ns).tolist() == [50_000_000] * (len(baseline.wheels) - 1)
    assert np.diff(baseline.imu.t_ns)[0] == 10_000_000


def test_motors_follow_commands_with_first_order_response(baseline):
    trace = baseline.trace
    t_s = (trace.t_ns - trace.t_ns[0]) * 1e-9
    tau = baseline.config.motor_tau_s
    # the first command (4 rad/s) starts at t = 1 s from rest
    at_tau = np.searchsorted(t_s, 1.0 + tau)
    assert trace.omega_l[at_tau] == pytest.approx(4.0 * (1 - np.exp(-1)), rel=0.02)
    assert trace.omega_l[np.searchsorted(t_s, 2.9)] == pytest.approx(4.0, rel=1e-3)


def test_encoder_noise_is_added_to_the_measured_speeds_only():
    sim = simulate(scripted(encoder_noise_rad_s=0.1))
    noise = sim.wheels.omega_l - sim.wheels_true.omega_l
    assert 0.07 < np.std(noise) < 0.13
    clean = simulate(scripted())
    assert np.array_equal(clean.trace.poses, sim.trace.poses)


def test_planner_covers_the_input_space_and_stays_in_the_arena():
    start = time.perf_counter()
    sim = simulate(SimConfig(duration_s=60.0, seed=2))
    elapsed = time.perf_counter() - start
    kinds = set(sim.schedule.kind)
    assert set(COMMAND_KINDS) <= kinds
    left, right = sim.schedule.omega_l, sim.schedule.omega_r
    assert np.any((left > 0) & (right > 0)) and np.any((left < 0) & (right < 0))
    assert np.any(left * right < 0)
    radius = np.hypot(sim.trace.poses[:, 0], sim.trace.poses[:, 1])
    assert radius.max() < sim.config.arena_radius_m + 1.0
    assert sim.truth.path_length()[-1] > 10.0
    assert elapsed < 10.0


def test_sixty_seconds_of_lidar_take_seconds():
    sim = simulate(SimConfig(duration_s=60.0, seed=3))
    start = time.perf_counter()
    count = sum(1 for _ in sim.scans())
    elapsed = time.perf_counter() - start
    assert count == 599 or count == 600
    assert elapsed < 20.0


# ---------------------------------------------------------------------------- effects


def _effect_sim(name: str, strength: float, **options):
    return simulate(scripted(effects=(make_effect(name, strength, **options),)))


def test_time_offset_delays_the_motion(baseline):
    sim = _effect_sim('time_offset', 0.1)
    shift = 100  # 0.1 s on the 1 kHz grid
    assert np.allclose(sim.trace.twist[shift:], baseline.trace.twist[:-shift], atol=1e-9)


def test_first_order_lag_smooths_the_twist(baseline):
    sim = _effect_sim('first_order_lag', 0.3)
    t_s = (sim.trace.t_ns - sim.trace.t_ns[0]) * 1e-9
    i = np.searchsorted(t_s, 1.3)
    assert sim.trace.twist[i, 0] < 0.7 * baseline.trace.twist[i, 0]
    j = np.searchsorted(t_s, 2.95)  # settled again before the next command
    assert sim.trace.twist[j, 0] == pytest.approx(baseline.trace.twist[j, 0], rel=0.01)


def test_speed_slip_grows_with_speed(baseline):
    sim = _effect_sim('speed_slip', 0.2)
    v0 = baseline.trace.twist[:, 0]
    expected = v0 * (1 - np.minimum(0.2 * np.abs(v0), 0.8))
    assert np.allclose(sim.trace.twist[:, 0], expected)
    assert np.allclose(sim.trace.twist[:, 2], baseline.trace.twist[:, 2])


def test_ratio_yaw_slip_peaks_when_one_side_turns_twice_the_other(baseline):
    sim = _effect_sim('ratio_yaw_slip', 0.4)
    t_s = (sim.trace.t_ns - sim.trace.t_ns[0]) * 1e-9
    arc = np.searchsorted(t_s, 6.5)   # (2, 4) rad/s: ratio 0.5
    spin = np.searchsorted(t_s, 8.5)  # (-4, 4): counter-rotating, no loss
    assert sim.trace.twist[arc, 2] == pytest.approx(0.6 * baseline.trace.twist[arc, 2],
                                                    rel=0.01)
    assert sim.trace.twist[spin, 2] == pytest.approx(baseline.trace.twist[spin, 2])


def test_lateral_skid_adds_v_y_proportional_to_v_times_omega(baseline):
    sim = _effect_sim('lateral_skid', 0.1)
    v_x, v_y, omega = baseline.trace.twist.T
    assert np.allclose(sim.trace.twist[:, 1], v_y + 0.1 * v_x * omega)
    assert np.max(np.abs(sim.trace.twist[:, 1] - v_y)) > 1e-3


def test_direction_asymmetry_slows_reversing_only(baseline):
    sim = _effect_sim('direction_asymmetry', 0.2)
    t_s = (sim.trace.t_ns - sim.trace.t_ns[0]) * 1e-9
    forward, backward = np.searchsorted(t_s, 2.5), np.searchsorted(t_s, 4.5)
    assert sim.trace.twist[forward, 0] == pytest.approx(baseline.trace.twist[forward, 0])
    assert sim.trace.twist[backward, 0] == pytest.approx(0.8 * baseline.trace.twist[backward, 0])


def test_terrain_regime_after_a_time_and_in_a_region(baseline):
    sim = _effect_sim('terrain_regime', 0.3, mode='time', switch_frac=0.5)
    mask = sim.trace.masks['terrain_regime']
    t_s = (sim.trace.t_ns - sim.trace.t_ns[0]) * 1e-9
    assert np.array_equal(mask, t_s >= 4.5)
    scale = np.where(mask, 0.7, 1.0)
    assert np.allclose(sim.trace.twist[:, 2], baseline.trace.twist[:, 2] * scale)
    region = _effect_sim('terrain_regime', 0.3, mode='region', boundary_x_m=0.2)
    inside = region.trace.masks['terrain_regime']
    assert inside.any() and not inside.all()
    # decided on the pose before the regime: the baseline pose here
    assert np.array_equal(inside, baseline.trace.poses[:, 0] > 0.2)


def test_effects_compose():
    both = simulate(scripted(effects=(make_effect('speed_slip', 0.2),
                                      make_effect('lateral_skid', 0.1))))
    slip = _effect_sim('speed_slip', 0.2)
    v_x, v_y, omega = slip.trace.twist.T
    assert np.allclose(both.trace.twist[:, 1], v_y + 0.1 * v_x * omega)


def test_random_effect_is_seeded_and_in_range():
    draws = [random_effect(np.random.default_rng(seed)) for seed in range(60)]
    again = [random_effect(np.random.default_rng(seed)) for seed in range(60)]
    assert draws == again
    assert {effect.name for effect in draws} == set(EFFECT_NAMES)
    for effect in draws:
        spec = EFFECTS[effect.name]
        assert spec.low <= effect.strength <= spec.high


def test_bad_effects_and_configs_are_refused():
    with pytest.raises(ParameterError, match='unknown effect'):
        make_effect('mud')
    with pytest.raises(ParameterError, match='strength'):
        make_effect('speed_slip', -1.0)
    with pytest.raises(ParameterError, match='alpha_l'):
        SimConfig(true_params={'alpha_l': 1.5})
    with pytest.raises(ParameterError, match='script'):
        SimConfig(script=((0.0, 1.0, 1.0),))


# ---------------------------------------------------------------------------- scene and lidar


def test_primitives_intersect_analytically():
    origin = np.array([[0.0, 0.0, 1.0]] * 4)
    direction = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0],
                          [-1.0, 0.0, 0.0]])
    room = Room(-10.0, 10.0, -5.0, 5.0, 3.0)
    assert np.allclose(room.intersect(origin, direction), [10.0, 1.0, 5.0, 10.0])
    box = Box((2.0, -1.0, 0.0), (3.0, 1.0, 2.0))
    assert np.allclose(box.intersect(origin, direction), [2.0, np.inf, np.inf, np.inf])
    cylinder = Cylinder(0.0, 4.0, 0.5, 0.0, 0.5)
    up = cylinder.intersect(origin[:1], np.array([[0.0, 1.0, 0.0]]))
    assert np.isinf(up[0])  # passes above the 0.5 m drum
    down = np.array([[0.0, 4.0, -1.0]]) / np.sqrt(17.0)
    # misses the top cap (it crosses z = 0.5 at y = 2) and hits the mantle at y = 3.5
    assert cylinder.intersect(origin[:1], down)[0] == pytest.approx(3.5 / 4.0 * np.sqrt(17.0))
    short = np.array([[0.0, 3.0, -0.5]]) / np.sqrt(9.25)  # over the cap edge, onto the side
    assert cylinder.intersect(origin[:1], short)[0] == pytest.approx(3.5 / 3.0 * np.sqrt(9.25))
    top = np.array([[0.0, 4.0, -0.5]]) / np.sqrt(16.25)  # reaches z = 0.5 at y = 4: the cap
    assert cylinder.intersect(origin[:1], top)[0] == pytest.approx(np.sqrt(16.25))
    scene = Scene(room, (box,), (cylinder,))
    assert np.allclose(scene.cast(origin, direction), [2.0, 1.0, 5.0, 10.0])


def test_default_scene_has_structure_at_several_heights_outside_the_arena():
    scene = default_scene()
    heights = [box.hi[2] for box in scene.boxes] + [cyl.z_hi for cyl in scene.cylinders]
    assert len(heights) >= 20 and min(heights) < 1.0 < max(heights)
    assert any(box.lo[2] > 0.0 for box in scene.boxes)
    assert scene.inside(0.0, 0.0, margin_m=7.0 - 0.1)


def test_outdoor_scene_is_a_field_of_trees_around_a_clearing_seen_like_a_vlp16():
    scene = outdoor_scene(clearing_radius_m=8.8)
    assert isinstance(scene.room, Field) and not scene.boxes
    assert len(scene.cylinders) == 800  # 400 trees: a trunk and a crown each
    assert scene.inside(0.0, 0.0, margin_m=8.0) and not scene.inside(200.0, 0.0)
    # the vectorized cylinder pass hits what each cylinder alone hits
    origin = np.array([[0.0, 0.0, 0.7]] * 720)
    azimuth = np.radians(np.arange(720) * 0.5)
    direction = np.stack([np.cos(azimuth), np.sin(azimuth), np.zeros(720)], axis=-1)
    expected = np.full(720, np.inf)
    for cylinder in scene.cylinders:
        expected = np.minimum(expected, cylinder.intersect(origin, direction))
    assert np.array_equal(scene.cast(origin, direction), expected)
    assert np.isfinite(expected).mean() > 0.3  # a horizontal ray finds a trunk often enough
    config = SimConfig(duration_s=2.0, seed=1, scene='forest', scene_half_size_m=16.0,
                       arena_radius_m=8.0,
                       lidar=LidarConfig(azimuth_resolution_deg=1.0, max_range_m=100.0))
    scans = list(simulate(config).scans())
    points = np.mean([len(scan) for scan in scans])
    assert 4500 < points <= 16 * 360  # VLP-16-like: the sky returns nothing


def test_the_snow_field_is_sparse_and_the_plain_nearly_empty():
    clearing = 0.55 * 30.0
    snow, plain = make_scene('snowfield', 30.0), make_scene('plain', 30.0)
    forest = make_scene('forest', 30.0)
    for scene in (snow, plain):
        centres = np.array([(c.x, c.y) for c in scene.cylinders])
        assert np.all(np.hypot(centres[:, 0], centres[:, 1]) > clearing)
        assert scene.inside(0.0, 0.0, margin_m=clearing - 1.0)
    # a tree per 50 m2 against the forest's per 25 m2: a horizontal ray finds less
    origin = np.array([[0.0, 0.0, 0.7]] * 720)
    azimuth = np.radians(np.arange(720) * 0.5)
    direction = np.stack([np.cos(azimuth), np.sin(azimuth), np.zeros(720)], axis=-1)
    hits = [np.isfinite(s.cast(origin, direction)).mean() for s in (forest, snow, plain)]
    assert hits[0] > hits[1] > hits[2] and hits[2] < 0.05
    assert make_scene('snowfield', 30.0) == snow  # deterministic


def test_lidar_points_lie_on_the_scene_seen_from_the_pose_at_their_time():
    config = SimConfig(duration_s=4.0, seed=1, script=((3.0, -6.0, 6.0),),
                       lidar=LidarConfig(azimuth_resolution_deg=2.0, range_noise_m=0.0,
                                         mount_yaw_rad=0.3))
    sim = simulate(config)
    scans = list(sim.scans())
    assert len(scans) == 39 or len(scans) == 40
    scan = scans[25]  # spinning at ~1.6 rad/s
    assert np.all(np.diff(scan.t_rel_s) >= 0) and scan.t_rel_s.max() < 0.1
    assert scan.end_ns == scan.stamp_ns + round(scan.t_rel_s.max() * 1e9)
    assert set(scan.ring.tolist()) == set(range(16))
    stamps = scan.stamp_ns + np.round(scan.t_rel_s * 1e9).astype(np.int64)

    def residual(poses: np.ndarray) -> np.ndarray:
        mount = config.lidar.extrinsic()
        heading = poses[:, 2] + config.lidar.mount_yaw_rad
        c, s = np.cos(poses[:, 2]), np.sin(poses[:, 2])
        ox = poses[:, 0] + c * mount[0, 3] - s * mount[1, 3]
        oy = poses[:, 1] + s * mount[0, 3] + c * mount[1, 3]
        ch, sh = np.cos(heading), np.sin(heading)
        px = ox + ch * scan.xyz[:, 0] - sh * scan.xyz[:, 1]
        py = oy + sh * scan.xyz[:, 0] + ch * scan.xyz[:, 1]
        pz = mount[2, 3] + scan.xyz[:, 2]
        origin = np.stack([ox, oy, np.full_like(ox, mount[2, 3])], axis=-1)
        delta = np.stack([px, py, pz], axis=-1) - origin
        rng = np.linalg.norm(delta, axis=1)
        return np.abs(sim.scene.cast(origin, delta / rng[:, None]) - rng)

    exact = residual(sim.pose_at(stamps))
    assert np.median(exact) < 1e-6
    frozen = residual(sim.pose_at(np.full(stamps.shape, scan.stamp_ns)))
    assert np.median(frozen) > 0.01  # the motion distortion is real


# ---------------------------------------------------------------------------- bag and CSV

TYPESTORE = get_typestore(Stores.ROS2_JAZZY)


def _read_bag(path: Path) -> dict[str, list]:
    out: dict[str, list] = {}
    with Reader(path) as reader:
        for connection, t_ns, raw in reader.messages():
            msg = TYPESTORE.deserialize_cdr(raw, connection.msgtype)
            out.setdefault(connection.topic, []).append((t_ns, msg))
    return out


@pytest.fixture(scope='module')
def small_sim():
    return simulate(SimConfig(duration_s=3.0, seed=4,
                              lidar=LidarConfig(azimuth_resolution_deg=6.0)))


@pytest.mark.parametrize('storage', ['sqlite3', 'mcap'])
def test_write_bag_streams_every_sensor_and_the_truth_csv(tmp_path, small_sim, storage):
    bag, csv_path = write_bag(small_sim, tmp_path / 'drive', storage=storage)
    messages = _read_bag(bag)
    assert len(messages['/joint_states']) == 61
    assert len(messages['/imu']) == 301
    assert len(messages['/points']) == 29 or len(messages['/points']) == 30
    _, joint = messages['/joint_states'][30]
    assert list(joint.name) == ['front_left_wheel_joint', 'rear_left_wheel_joint',
                                'front_right_wheel_joint', 'rear_right_wheel_joint']
    assert joint.velocity[0] == pytest.approx(small_sim.wheels.omega_l[30])
    assert joint.velocity[3] == pytest.approx(small_sim.wheels.omega_r[30])
    _, cloud = messages['/points'][5]
    assert cloud.header.frame_id == 'lidar'
    fields = {f.name: f.datatype for f in cloud.fields}
    assert fields['t'] == 7  # FLOAT32
    assert 'ring' in fields
    _, tf = messages['/tf_static'][0]
    transform = tf.transforms[0]
    assert (transform.header.frame_id, transform.child_frame_id) == ('base_link', 'lidar')
    assert transform.transform.translation.x == pytest.approx(0.3)
    times = [t for topic in messages.values() for t, _ in topic]
    assert len(times) == sum(len(v) for v in messages.values())
    with open(csv_path, newline='') as handle:
        rows = list(csv.DictReader(handle))
    assert len(rows) == 61
    assert {'t', 'wheel_left', 'wheel_right', 'x', 'y', 'yaw'} <= set(rows[0])
    assert float(rows[40]['x']) == pytest.approx(small_sim.truth.x[40], abs=1e-8)
    assert float(rows[40]['wheel_left']) == pytest.approx(small_sim.wheels.omega_l[40])


def test_write_bag_point_time_conventions(tmp_path, small_sim):
    bag, _ = write_bag(small_sim, tmp_path / 'ns', point_time='rel_ns_u32')
    _, cloud = _read_bag(bag)['/points'][3]
    fields = {f.name: f for f in cloud.fields}
    assert fields['t'].datatype == 6  # UINT32
    bag, _ = write_bag(small_sim, tmp_path / 'abs', point_time='abs_s_f64', stamp_at='end')
    _, cloud = _read_bag(bag)['/points'][3]
    fields = {f.name: f for f in cloud.fields}
    assert fields['timestamp'].datatype == 8  # FLOAT64
    stamp_ns = cloud.header.stamp.sec * 10**9 + cloud.header.stamp.nanosec
    data = np.frombuffer(cloud.data, dtype=np.uint8).reshape(-1, cloud.point_step)
    offset = fields['timestamp'].offset
    absolute = data[:, offset:offset + 8].copy().view(np.float64).ravel()
    assert absolute.max() == pytest.approx(stamp_ns * 1e-9, abs=1e-5)
    with pytest.raises(ParameterError, match='uint32'):
        write_bag(small_sim, tmp_path / 'bad', point_time='rel_ns_u32', stamp_at='end')


def _fine_step(effect, target, t_s):
    """Run one dynamics effect on a given twist on a fine grid (v_x, v_y, omega columns)."""
    data = EffectInput(t_s, np.zeros(t_s.size), np.zeros(t_s.size), target, None, t_s[-1])
    return effect.apply_twist(data)


def test_per_component_lags_act_on_one_component_as_continuous_responses():
    t_s = np.arange(0.0, 2.0, 0.001)
    step = np.where(t_s >= 0.5, 1.0, 0.0)
    target = np.stack([step, 0.3 * step, 0.5 * step], axis=-1)
    for name, lagged in (('forward_lag', 0), ('yaw_lag', 2)):
        out = _fine_step(make_effect(name, 0.2), target, t_s)
        after = np.searchsorted(t_s, 0.7)  # 0.2 s after the step: 1 - 1/e of the way
        assert out[after, lagged] == pytest.approx(target[after, lagged] * (1 - math.exp(-1)),
                                                   rel=0.02), name
        others = [c for c in range(3) if c != lagged]
        assert np.array_equal(out[:, others], target[:, others]), name


def test_acceleration_slip_lags_only_while_the_wheels_speed_up():
    t_s = np.arange(0.0, 3.0, 0.001)
    # speed up to 1 m/s at 0.5 s, down to 0.2 m/s at 2 s
    v = np.where(t_s >= 0.5, 1.0, 0.0) - np.where(t_s >= 2.0, 0.8, 0.0)
    target = np.stack([v, np.zeros_like(v), 0.4 * v], axis=-1)
    out = _fine_step(make_effect('acceleration_slip', 0.15), target, t_s)
    rising = np.searchsorted(t_s, 0.65)
    assert out[rising, 0] == pytest.approx(1 - math.exp(-1), rel=0.02)  # lags speeding up
    falling = np.searchsorted(t_s, 2.002)
    assert out[falling, 0] == pytest.approx(0.2)  # follows at once slowing down
    assert np.array_equal(out[:, 2], target[:, 2])  # the yaw rate is untouched
    # backward too: speeding up backward lags
    back = _fine_step(make_effect('acceleration_slip', 0.15), -target, t_s)
    assert back[rising, 0] == pytest.approx(-(1 - math.exp(-1)), rel=0.02)
