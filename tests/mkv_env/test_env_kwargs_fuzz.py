"""Out-of-range and odd ``gymnasium.make`` kwargs (hypothesis): either the env is made and runs
with finite observations, or a one-line ValueError names the value. Never another exception and
never an abort of the interpreter (Chipmunk aborts on a negative mass or NaN friction, which is
why the parameters are validated where they enter)."""

import math

import gymnasium as gym
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import mkv_env  # noqa: F401
from mkv_env.params import RobotParams

ROBOT_FIELDS = [f for f in RobotParams.__dataclass_fields__ if not f.endswith("_motor")
                and f != "caster_xy_m"]
ODD_NUMBERS = st.one_of(
    st.sampled_from([0, -1, -1e-9, 1e-300, 1e300, math.nan, math.inf, -math.inf, 0.5, 2.0]),
    st.floats(allow_nan=True, allow_infinity=True, width=64),
    st.text(max_size=3), st.lists(st.integers(), max_size=2), st.none(), st.booleans())


def outcome(kwargs):
    try:
        env = gym.make("MKVJam-v0", **kwargs)
        obs, _ = env.reset(seed=0)  # a jam must be buildable with these parameters
    except ValueError as e:
        assert "\n" not in str(e) and str(e)
        return "refused"
    for a in ([2, 1], [0, 0], [2, 2], [1, 1]) * 5:
        obs, r, *_ = env.step(np.array(a))
        assert np.all(np.isfinite(obs)) and math.isfinite(r)
    env.close()
    return "ran"


@settings(max_examples=120, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(field=st.sampled_from(ROBOT_FIELDS), value=ODD_NUMBERS)
def test_robot_params(field, value):
    outcome({"robot_params": {field: value}})


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(motor=st.sampled_from(["drive_motor", "steer_motor"]),
       field=st.sampled_from(["supply_v", "resistance_ohm", "k_nm_per_a", "viscous_nms",
                              "inertia_kgm2"]),
       value=ODD_NUMBERS)
def test_motor_params(motor, field, value):
    outcome({"robot_params": {motor: {field: value}}})


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(channel=st.sampled_from(["compass", "drive_current", "bump_rear"]),
       field=st.sampled_from(["low", "high", "noise_std", "quantum", "bias"]),
       value=ODD_NUMBERS)
def test_sensor_params(channel, field, value):
    outcome({"sensor_params": {channel: {field: value}}})


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(key=st.sampled_from(["sensor_params", "robot_params", "sensor_noise", "n_clutter",
                            "substeps", "control_period_s", "escape_forward_m",
                            "progress_reward"]),
       value=ODD_NUMBERS)
def test_env_kwargs(key, value):
    outcome({key: value})


@pytest.mark.parametrize("kwargs", [
    {"robot_params": {"mass_kg": -1}}, {"robot_params": {"mass_kg": math.nan}},
    {"robot_params": {"chassis_friction": math.nan}}, {"robot_params": {"chassis_friction": -1}},
    {"robot_params": {"tire_friction": -1}}, {"robot_params": {"length_m": 0}},
    {"robot_params": {"steer_limit_rad": -1}}, {"robot_params": {"drive_load_fraction": 1.5}},
    {"robot_params": {"mass_kg": 0}}, {"robot_params": {"drive_wheel_radius_m": 0}},
    {"sensor_params": 5}, {"sensor_params": [1]},
    {"sensor_params": {"compass": {"noise_std": -1}}},
    {"sensor_params": {"compass": {"quantum": -0.1}}},
])
def test_the_reported_cases_are_refused(kwargs):
    assert outcome(kwargs) == "refused"
