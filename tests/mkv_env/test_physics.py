"""Physical sanity of the MK-V model: motors, traction, steering stops, coasting, skidding."""

import math

import numpy as np
from conftest import FWD, LEFT, OFF, REV, RIGHT, ch, open_floor, place, run, speed
from hypothesis import given, settings
from hypothesis import strategies as st

from mkv_env.params import RobotParams

STALL_A = RobotParams().drive_motor.stall_current_a  # 0.5 A
STEER_STALL_A = RobotParams().steer_motor.stall_current_a  # 0.4 A


def test_forward_on_open_floor_advances_encoder_and_pose_with_low_current(floor_env):
    env = floor_env
    out = run(env, (FWD, OFF), 20)
    obs, _, _, _, info = out[-1]
    x, y, th = info["pose"]
    assert x > 2.0 + 0.4  # ~0.27 m/s for ~2 s
    assert abs(y - 2.0) < 0.01 and abs(th) < 0.01
    assert ch(env, obs, "drive_ticks") > 10
    p = RobotParams()  # no slip: both wheels roll the same distance
    rolled_drive = ch(env, obs, "drive_ticks") * p.drive_wheel_radius_m
    rolled_roller = ch(env, obs, "roller_ticks") * p.steer_wheel_radius_m
    assert abs(rolled_drive - rolled_roller) <= 1.0 * p.drive_wheel_radius_m
    assert 0 < ch(env, obs, "drive_current") < 0.3 * STALL_A
    assert not info["stuck"] and not info["bumped"]
    assert abs(info["distance_m"] - (x - 2.0)) < 1e-6


def test_reverse_is_symmetric_to_forward():
    fwd = open_floor()
    rev = open_floor()
    a = run(fwd, (FWD, OFF), 15)
    b = run(rev, (REV, OFF), 15)
    for (oa, *_, ia), (ob, *_, ib) in zip(a, b, strict=True):
        assert np.allclose(ia["pose"][0] - 2.0, -(ib["pose"][0] - 2.0), atol=1e-9)
        for name in ("drive_ticks", "drive_current"):
            assert abs(ch(fwd, oa, name) + ch(rev, ob, name)) <= 1.0 + 1e-6


def test_driving_into_a_wall_stalls_with_near_stall_current_and_stuck():
    env = open_floor()
    place(env, (3.5, 2.0, 0.0))  # facing the x = 4 wall, 0.33 m to go
    out = run(env, (FWD, OFF), 30)
    obs, _, _, _, info = out[-1]
    assert info["stuck"] and info["bumped"] and info["jams"] == 1
    assert ch(env, obs, "bump_front_left") == 1 and ch(env, obs, "bump_front_right") == 1
    assert ch(env, obs, "drive_current") > 0.9 * STALL_A
    assert abs(ch(env, obs, "drive_ticks")) <= 1  # the wheel stalls: traction > stall force
    assert info["pose"][0] < 4.0 - 0.15  # nothing tunnels through the wall


def test_blocked_drive_wheel_spins_on_a_slippery_floor():
    env = open_floor(n_patches=0)
    env.world.layout.patches.append((0.0, 0.0, 4.0, 4.0, 0.3))
    place(env, (3.5, 2.0, 0.0))
    obs, _, _, _, info = run(env, (FWD, OFF), 30)[-1]
    assert info["stuck"]
    assert ch(env, obs, "drive_ticks") > 5  # the wheel turns ...
    assert abs(ch(env, obs, "roller_ticks")) <= 1  # ... the robot does not
    assert ch(env, obs, "drive_current") < 0.8 * STALL_A  # spinning draws less than stall


def test_steering_hits_its_stop_and_steering_current_rises(floor_env):
    env = floor_env
    limit = RobotParams().steer_limit_rad
    moving = run(env, (OFF, LEFT), 2)[-1][0]
    assert 0 < ch(env, moving, "steer_angle") < limit
    assert abs(ch(env, moving, "steer_current")) < 0.5 * STEER_STALL_A
    at_stop = run(env, (OFF, LEFT), 10)[-1][0]
    assert abs(ch(env, at_stop, "steer_angle") - limit) < 0.01
    assert ch(env, at_stop, "steer_current") > 0.9 * STEER_STALL_A
    right = run(env, (OFF, RIGHT), 15)[-1][0]
    assert abs(ch(env, right, "steer_angle") + limit) < 0.01
    assert ch(env, right, "steer_current") < -0.9 * STEER_STALL_A


def test_steered_robot_turns_towards_the_steering_side(floor_env):
    env = floor_env
    run(env, (OFF, LEFT), 10)
    _, _, _, _, info = run(env, (FWD, OFF), 10)[-1]
    assert info["pose"][2] > 0.3  # turned left (counter-clockwise)


def test_off_coasts_to_rest(floor_env):
    env = floor_env
    run(env, (FWD, OFF), 10)
    assert speed(env) > 0.2
    out = run(env, (OFF, OFF), 10)
    assert speed(env) < 0.005
    assert ch(env, out[-1][0], "drive_ticks") == 0
    assert not out[-1][4]["stuck"]  # not commanded to move: not stuck


def test_pushed_sideways_the_robot_skids_as_far_as_its_traction_allows(floor_env):
    """A sideways shove makes both wheels slide; friction mu*N stops it in v^2 / (2 a)."""
    env = floor_env
    p = RobotParams()
    decel = p.tire_friction * 9.81 * (p.drive_load_fraction + p.steer_load_fraction)

    def slide(v0):
        place(env, (2.0, 2.0, 0.0))
        env.world.robot.body.velocity = (0.0, v0)
        for _ in range(10):
            env.world.step(0, 0, 0.1, 4)
        return env.world.robot.pose()[1] - 2.0

    # continuous v^2/(2a) = 7.6 cm; semi-implicit Euler with substep h adds v*h/2 (1.25 cm)
    expected = 1.0**2 / (2 * decel) + 1.0 * 0.025 / 2
    assert 0.9 * expected < slide(1.0) < 1.1 * expected
    assert slide(0.05) < 0.002  # a nudge is absorbed within a substep


@settings(max_examples=25, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 2), st.integers(0, 2)), min_size=5, max_size=40),
       st.integers(0, 2**31 - 1))
def test_any_action_sequence_keeps_state_finite_and_inside_the_arena(actions, seed):
    env = open_floor(n_clutter=14, n_patches=2, sensor_noise=1.0)
    env.reset(seed=seed)
    for a in actions:
        obs, r, *_, info = env.step(np.array(a))
        assert np.all(np.isfinite(obs)) and np.isfinite(r)
        assert env.observation_space.contains(obs)
        x, y, _ = info["pose"]
        assert 0.0 < x < 4.0 and 0.0 < y < 4.0


def test_rolling_follows_the_bicycle_model(floor_env):
    """Without sliding the path curvature is tan(steer) / wheelbase (non-holonomic wheels)."""
    env = floor_env
    run(env, (OFF, LEFT), 10)
    run(env, (FWD, LEFT), 15)
    p = RobotParams()
    b = env.world.robot.body
    v = b.velocity_at_local_point((p.drive_x_m, 0.0))
    u_rear = math.cos(b.angle) * v.x + math.sin(b.angle) * v.y
    curvature = b.angular_velocity / u_rear
    expected = math.tan(env.world.robot.state.steer) / (p.steer_x_m - p.drive_x_m)
    assert u_rear > 0.1
    assert abs(curvature - expected) < 0.03 * expected
