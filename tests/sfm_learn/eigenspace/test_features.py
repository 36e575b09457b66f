"""FeatureSpec / FeatureBuilder: layout, episode resets, batch == online, serialisation."""

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mkv_env.features import FeatureBuilder, FeatureSpec

OBS = ["drive_current", "steer_current", "bump_fl", "bump_fr", "heading"]


def recording(t_len, n_obs=5, nvec=(3, 3), p_start=0.1, seed=0):
    rng = np.random.default_rng(seed)
    obs = rng.standard_normal((t_len, n_obs)).astype(np.float32)
    actions = np.stack([rng.integers(0, n, t_len) for n in nvec], axis=1)
    starts = rng.random(t_len) < p_start
    return obs, actions, starts


def run_online(builder, obs, actions, starts):
    rows = []
    for t in range(len(obs)):
        if t == 0 or starts[t]:
            builder.reset()
        rows.append(builder.step(obs[t], actions[t - 1] if t > 0 else None))
    return np.array(rows).reshape(len(obs), builder.n_features)


specs = st.builds(
    FeatureSpec,
    obs_names=st.just(OBS),
    channels=st.one_of(st.none(), st.lists(st.sampled_from(OBS), unique=True, max_size=5)),
    history=st.integers(0, 4),
    history_channels=st.one_of(st.none(), st.lists(st.sampled_from(OBS), unique=True, min_size=1)),
    history_pad=st.sampled_from(["edge", "zero"]),
    trace_decays=st.lists(st.floats(0.0, 0.99), max_size=3),
    trace_channels=st.one_of(st.none(), st.lists(st.sampled_from(OBS), unique=True, min_size=1)),
    prev_action=st.sampled_from(["none", "signed", "onehot"]),
)


@settings(max_examples=60, deadline=None)
@given(spec=specs, t_len=st.integers(1, 60), p_start=st.sampled_from([0.0, 0.1, 0.5]),
       seed=st.integers(0, 1000))
def test_batch_transform_equals_online_steps_exactly(spec, t_len, p_start, seed):
    obs, actions, starts = recording(t_len, p_start=p_start, seed=seed)
    builder = FeatureBuilder(spec)
    batch = builder.transform(obs, actions, starts)
    assert batch.shape == (t_len, len(builder.feature_names))
    np.testing.assert_array_equal(batch, run_online(FeatureBuilder(spec), obs, actions, starts))


@settings(max_examples=30, deadline=None)
@given(spec=specs, seed=st.integers(0, 1000))
def test_an_episode_does_not_see_the_previous_one(spec, seed):
    obs, actions, starts = recording(40, seed=seed)
    starts[:] = False
    starts[20] = True
    builder = FeatureBuilder(spec)
    base = builder.transform(obs, actions, starts)
    obs2, actions2 = obs.copy(), actions.copy()
    obs2[:20] = 100.0
    actions2[:20] = 0
    np.testing.assert_array_equal(builder.transform(obs2, actions2, starts)[20:], base[20:])
    # the second episode alone gives the same rows
    np.testing.assert_array_equal(builder.transform(obs[20:], actions[20:]), base[20:])


@settings(max_examples=20, deadline=None)
@given(spec=specs)
def test_spec_round_trips_through_json(spec):
    data = json.loads(json.dumps(spec.to_dict()))
    again = FeatureSpec.from_dict(data)
    assert again == spec
    assert FeatureBuilder.from_dict(data).feature_names == FeatureBuilder(spec).feature_names
    obs, actions, starts = recording(30)
    np.testing.assert_array_equal(FeatureBuilder(again).transform(obs, actions, starts),
                                  FeatureBuilder(spec).transform(obs, actions, starts))


def test_feature_names_and_layout():
    spec = FeatureSpec(obs_names=OBS, channels=["drive_current", "bump_fl"], history=2,
                       history_channels=["drive_current"], trace_decays=[0.8],
                       trace_channels=["bump_fl"], prev_action="onehot")
    assert FeatureBuilder(spec).feature_names == [
        "drive_current[t]", "bump_fl[t]",
        "drive_current[t-1]", "drive_current[t-2]",
        "bump_fl~0.8",
        "drive[t-1]=0", "drive[t-1]=1", "drive[t-1]=2",
        "steer[t-1]=0", "steer[t-1]=1", "steer[t-1]=2",
    ]
    signed = FeatureSpec(obs_names=OBS, channels=[], prev_action="signed")
    assert FeatureBuilder(signed).feature_names == ["drive[t-1]", "steer[t-1]"]


def test_history_is_the_lagged_observation_within_an_episode():
    obs = np.arange(10.0)[:, None] * np.ones((1, len(OBS)))
    starts = np.zeros(10, bool)
    starts[6] = True
    edge = FeatureBuilder(FeatureSpec(obs_names=OBS, channels=["heading"], history=2,
                                      history_channels=["heading"]))
    f = edge.transform(obs, episode_start=starts)
    np.testing.assert_array_equal(f[:, 0], np.arange(10.0))
    np.testing.assert_array_equal(f[:, 1], [0, 0, 1, 2, 3, 4, 6, 6, 7, 8])
    np.testing.assert_array_equal(f[:, 2], [0, 0, 0, 1, 2, 3, 6, 6, 6, 7])
    zero = FeatureBuilder(FeatureSpec(obs_names=OBS, channels=[], history=2,
                                      history_channels=["heading"], history_pad="zero"))
    g = zero.transform(obs + 1, episode_start=starts)
    np.testing.assert_array_equal(g[:, 0], [0, 1, 2, 3, 4, 5, 0, 7, 8, 9])
    np.testing.assert_array_equal(g[:, 1], [0, 0, 1, 2, 3, 4, 0, 0, 7, 8])


def test_trace_is_an_exponential_moving_average_from_the_episode_start():
    d = 0.8
    obs = np.zeros((12, len(OBS)))
    obs[2:, 2] = 1.0  # bump from step 2 on
    builder = FeatureBuilder(FeatureSpec(obs_names=OBS, channels=[], trace_decays=[d],
                                         trace_channels=["bump_fl"]))
    f = builder.transform(obs)[:, 0]
    k = np.arange(12) - 1
    np.testing.assert_allclose(f, np.where(k >= 1, 1 - d ** k.clip(0), 0.0), rtol=1e-12)
    # a constant signal is its own trace, including at an episode start
    const = FeatureBuilder(FeatureSpec(obs_names=OBS, trace_decays=[0.5, 0.9]))
    x = np.full((5, len(OBS)), 3.25)
    np.testing.assert_array_equal(const.transform(x)[:, len(OBS):], 3.25)


def test_previous_command_encoding():
    obs = np.zeros((4, len(OBS)))
    actions = np.array([[0, 2], [1, 0], [2, 1], [0, 0]])
    starts = np.array([True, False, False, True])
    signed = FeatureBuilder(FeatureSpec(obs_names=OBS, channels=[], prev_action="signed"))
    np.testing.assert_array_equal(signed.transform(obs, actions, starts),
                                  [[0, 0], [-1, 1], [0, -1], [0, 0]])
    onehot = FeatureBuilder(FeatureSpec(obs_names=OBS, channels=[], prev_action="onehot"))
    np.testing.assert_array_equal(onehot.transform(obs, actions, starts),
                                  [[0, 0, 0, 0, 0, 0], [1, 0, 0, 0, 0, 1],
                                   [0, 1, 0, 1, 0, 0], [0, 0, 0, 0, 0, 0]])


def test_online_prev_action_is_ignored_right_after_reset():
    builder = FeatureBuilder(FeatureSpec(obs_names=OBS, channels=[], prev_action="signed"))
    builder.reset()
    np.testing.assert_array_equal(builder.step(np.zeros(len(OBS)), prev_action=[2, 2]), [0, 0])
    np.testing.assert_array_equal(builder.step(np.zeros(len(OBS)), prev_action=[2, 0]), [1, -1])


@pytest.mark.parametrize("kwargs, match", [
    ({"channels": ["nope"]}, r"channels has unknown channel\(s\) \['nope'\]; valid channels"),
    ({"trace_channels": ["x"]}, r"trace_channels has unknown channel"),
    ({"history": -1}, r"history must be an int in \[0, 1000\]; got -1"),
    ({"trace_decays": [1.0]}, r"trace_decays must be in \[0, 1\); got \[1.0\]"),
    ({"prev_action": "last"}, r"prev_action must be one of"),
    ({"history_pad": "mirror"}, r"history_pad must be one of"),
    ({"channels": "heading"}, r"must be a sequence of names"),
])
def test_bad_specs_are_rejected_with_the_value(kwargs, match):
    with pytest.raises(ValueError, match=match):
        FeatureSpec(obs_names=OBS, **kwargs)


def test_from_dict_rejects_unknown_keys_and_versions():
    data = FeatureSpec(obs_names=OBS).to_dict()
    with pytest.raises(ValueError, match=r"unknown feature spec key\(s\) \['extra'\]"):
        FeatureSpec.from_dict({**data, "extra": 1})
    with pytest.raises(ValueError, match="version 99 is not supported"):
        FeatureSpec.from_dict({**data, "version": 99})


def test_bad_inputs_are_rejected():
    builder = FeatureBuilder(FeatureSpec(obs_names=OBS, prev_action="signed"))
    obs, actions, starts = recording(10)
    with pytest.raises(ValueError, match="actions are required"):
        builder.transform(obs)
    with pytest.raises(ValueError, match=r"observations must have shape \(T, n_obs\)"):
        builder.transform(obs[:, :3], actions)
    with pytest.raises(ValueError, match=r"action indices must be in \[0, nvec\)"):
        builder.transform(obs, actions + 3)
    with pytest.raises(ValueError, match=r"episode_start must have shape \(10,\)"):
        builder.transform(obs, actions, starts[:5])
