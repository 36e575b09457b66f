"""One sensor-name tuple and one action-space definition that everything reads."""

import gymnasium as gym

import mkv_env  # noqa: F401
from mkv_env import actions, params, sensors, teacher
from mkv_env.features import FeatureSpec, default_feature_spec
from sfm_learn.baselines import bc


def test_every_reader_sees_the_same_sensor_names_and_actions():
    for env_id in ("MKV-v0", "MKVJam-v0"):
        env = gym.make(env_id)
        assert tuple(env.unwrapped.sensor_names) == params.SENSOR_NAMES
        assert env.action_space == actions.action_space()
        env.close()
    assert tuple(params.DEFAULT_CHANNELS) == params.SENSOR_NAMES
    assert teacher.SENSOR_NAMES is params.SENSOR_NAMES
    assert sensors.SENSOR_NAMES is params.SENSOR_NAMES
    assert bc.ACTION_NVEC is actions.ACTION_NVEC and bc.VALUE_NAMES is actions.VALUE_NAMES
    spec = default_feature_spec(params.SENSOR_NAMES)
    assert spec.action_nvec == actions.ACTION_NVEC
    assert FeatureSpec(obs_names=params.SENSOR_NAMES).action_names == actions.ACTION_NAMES


def test_the_value_names_match_the_indices():
    assert actions.VALUE_NAMES["drive"][actions.REVERSE] == "reverse"
    assert actions.VALUE_NAMES["drive"][actions.FORWARD] == "forward"
    assert actions.VALUE_NAMES["steer"][actions.LEFT] == "left"
    assert actions.VALUE_NAMES["steer"][actions.RIGHT] == "right"
    assert all(v[actions.OFF] == "off" for v in actions.VALUE_NAMES.values())
