"""SfMPolicy: quantisation, fitting, files, sensor-layout checks, and the seeded science."""

import gymnasium as gym
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

import mkv_env  # noqa: F401
from mkv_env.dataset import build
from mkv_env.features import FeatureSpec, default_feature_spec
from mkv_env.policies import PolicySpecError, make_policy
from sfm_learn.eigenspace.policy import (
    PolicyFileError,
    SfMPolicy,
    episode_starts,
    fit_policy,
    learn_thresholds,
    min_fit_rows,
    onehot_actions,
    preset,
    quantise,
    rare_channels,
    signed_actions,
)
from sfm_learn.evaluation import evaluate
from sfm_learn.evaluation.compare import compare


# ---------------------------------------------------------------- quantisation
def test_quantise_maps_values_to_reverse_off_forward():
    thr = np.array([[-0.5, 0.5], [-0.2, 0.3]])
    v = np.array([[-0.6, -0.21], [-0.5, -0.2], [0.5, 0.3], [0.51, 0.31]])
    assert quantise(v, thr).tolist() == [[0, 0], [1, 1], [1, 1], [2, 2]]


@given(st.lists(st.floats(-5, 5), min_size=2, max_size=50),
       st.floats(-2, 2), st.floats(0, 2))
def test_quantise_is_monotone_in_the_value(values, lo, width):
    thr = np.array([[lo, lo + width]])
    v = np.sort(np.array(values))[:, None]
    q = quantise(v, thr)[:, 0]
    assert set(q.tolist()) <= {0, 1, 2}
    assert np.all(np.diff(q) >= 0)


def test_learned_thresholds_separate_separable_classes():
    rng = np.random.default_rng(0)
    a = rng.integers(0, 3, 600)
    v = (a - 1) * 0.3 + rng.uniform(-0.1, 0.1, a.size) + 0.2  # shifted: fixed +-0.5 fails
    thr = learn_thresholds(v[:, None], a[:, None])
    assert np.mean(quantise(v[:, None], thr)[:, 0] == a) == 1.0
    assert np.mean(quantise(v[:, None], [[-0.5, 0.5]])[:, 0] == a) < 0.8


def test_action_encodings():
    a = np.array([[0, 2], [1, 1], [2, 0]])
    assert signed_actions(a, (3, 3)).tolist() == [[-1, 1], [0, 0], [1, -1]]
    oh = onehot_actions(a, (3, 3))
    assert oh.shape == (3, 6) and oh.sum(axis=1).tolist() == [2, 2, 2]
    assert oh[0].tolist() == [1, 0, 0, 0, 0, 1]


# ---------------------------------------------------------------- fitting and files
@pytest.fixture(scope="module")
def policy(small_train):
    return fit_policy(small_train)


def test_fit_uses_the_default_features_and_records_its_training(policy, small_train):
    assert policy.feature_spec == default_feature_spec(small_train.sensor_names)
    assert policy.sensor_names == tuple(small_train.sensor_names)
    assert policy.training["rows"] == small_train.n_steps
    assert policy.training["datasets"][0]["sha256"] == small_train.metadata["content_sha256"]
    assert 1 <= policy.n_components <= policy.projector.n_known_
    assert policy.thresholds.shape == (2, 2)


def test_save_load_round_trip_predicts_identically(policy, small_train, tmp_path):
    path = policy.save(tmp_path / "p.npz")
    back = SfMPolicy.load(path)
    obs, act = small_train["observations"], small_train["actions"]
    starts = episode_starts(small_train)
    np.testing.assert_array_equal(back.batch_values(obs, act, starts),
                                  policy.batch_values(obs, act, starts))
    assert back.feature_spec == policy.feature_spec and back.env_id == "MKV-v0"
    assert back.metadata() == policy.metadata()


def test_online_predict_equals_the_batch_path_on_its_own_episode(policy):
    env = gym.make("MKV-v0", max_episode_steps=80)
    obs, _ = env.reset(seed=3)
    policy.reset()
    observations, actions = [], []
    for _ in range(80):
        a, state = policy.predict(obs)
        assert state is None and a.dtype == np.int64 and a.shape == (2,)
        observations.append(obs)
        actions.append(a)
        obs, _, term, trunc, _ = env.step(a)
        if term or trunc:
            break
    starts = np.zeros(len(actions), dtype=bool)
    starts[0] = True
    np.testing.assert_array_equal(policy.batch_predict(np.array(observations),
                                                       np.array(actions), starts),
                                  np.array(actions))


def test_episode_start_resets_the_feature_state(policy, small_train):
    obs = small_train["observations"]
    policy.reset()
    first = policy.predict(obs[0])[0]
    for o in obs[1:30]:
        policy.predict(o)
    again = policy.predict(obs[0], episode_start=True)[0]
    np.testing.assert_array_equal(first, again)


def test_batch_predict_keeps_one_feature_state_per_env(policy, small_train):
    """A batch of two envs equals two policies run one observation at a time (SB3 contract)."""
    obs = small_train["observations"]
    a, b = obs[:40], obs[100:140]
    policy.reset()
    batch = [policy.predict(np.stack([x, y]), episode_start=np.array([t == 0, t == 0]))[0]
             for t, (x, y) in enumerate(zip(a, b, strict=True))]
    singles = []
    for run in (a, b):
        policy.reset()
        singles.append([policy.predict(x, episode_start=(t == 0))[0] for t, x in enumerate(run)])
    np.testing.assert_array_equal(np.stack(batch)[:, 0], np.stack(singles[0]))
    np.testing.assert_array_equal(np.stack(batch)[:, 1], np.stack(singles[1]))
    # restarting env 1 alone leaves env 0's state alone
    policy.reset()
    for t in range(20):
        policy.predict(np.stack([a[t], b[t]]), episode_start=np.array([t == 0, t == 0]))
    got = policy.predict(np.stack([a[20], b[0]]), episode_start=np.array([False, True]))[0]
    np.testing.assert_array_equal(got[0], singles[0][20])
    np.testing.assert_array_equal(got[1], singles[1][0])


@pytest.mark.parametrize("shape", [(3,), (2, 3), (1, 2, 10), (0, 10)])
def test_predict_rejects_other_shapes(policy, shape):
    with pytest.raises(ValueError, match=r"shape \(n_envs, 10\)"):
        policy.predict(np.zeros(shape))


def test_load_refuses_a_different_sensor_layout(policy, tmp_path):
    path = policy.save(tmp_path / "p.npz")
    env = gym.make("MKV-v0")

    class Other:
        unwrapped = type("U", (), {"sensor_names": ("a", "b")})()
        action_space = env.action_space

    with pytest.raises(PolicyFileError, match=r"fitted on sensors \[drive_ticks.*env has \[a, b\]"):
        SfMPolicy.load(path, Other())
    with pytest.raises(PolicySpecError, match="fitted on sensors"):
        make_policy(f"sfm:{path}", Other())
    assert make_policy(f"sfm:{path}", env).n_components == policy.n_components


@pytest.mark.parametrize("content", [b"", b"not a zip", None])
def test_load_of_a_bad_file_is_one_clear_error(tmp_path, content, small_train):
    path = tmp_path / "bad.npz"
    if content is None:  # a dataset is an npz too, but not a policy
        from mkv_env.dataset import save

        save(small_train, path)
    else:
        path.write_bytes(content)
    with pytest.raises(PolicyFileError, match="bad.npz") as e:
        SfMPolicy.load(path)
    assert "\n" not in str(e.value)
    with pytest.raises(PolicyFileError, match="does not exist"):
        SfMPolicy.load(tmp_path / "missing.npz")


def _rewrite(path, out, meta_edit=None, arrays_edit=None):
    """Copy policy file ``path`` to ``out`` with its metadata / arrays changed."""
    import io
    import json
    import zipfile

    with zipfile.ZipFile(path) as zf:
        meta = json.loads(zf.read("metadata.json"))
        arrays = {n[:-4]: np.load(io.BytesIO(zf.read(n))) for n in zf.namelist()
                  if n.endswith(".npy")}
    if meta_edit:
        meta = meta_edit(meta)
    if arrays_edit:
        arrays_edit(arrays)
    with zipfile.ZipFile(out, "w") as zf:
        for k, a in arrays.items():
            buf = io.BytesIO()
            np.save(buf, a)
            zf.writestr(k + ".npy", buf.getvalue())
        zf.writestr("metadata.json", json.dumps(meta))
    return out


def _to_version_1(arrays):
    """The format-1 layout: run-time arrays without prefix, no training statistics."""
    for k in ("mean_", "scale_", "components_", "singular_values_", "coef_", "intercept_"):
        arrays[k] = arrays.pop(f"projector.{k}")
    for k in [k for k in arrays if k.startswith("projector.")]:
        arrays.pop(k)


def test_format_1_files_still_load_and_predict_the_same(policy, small_train, tmp_path):
    path = policy.save(tmp_path / "p.npz")
    v1 = _rewrite(path, tmp_path / "v1.npz", lambda m: {**m, "format_version": 1},
                  _to_version_1)
    old = SfMPolicy.load(v1)
    obs, act = small_train["observations"], small_train["actions"]
    starts = small_train["step"] == 0
    np.testing.assert_array_equal(old.batch_predict(obs, act, starts),
                                  policy.batch_predict(obs, act, starts))
    with pytest.raises(ValueError, match="without its training statistics"):
        old.projector.partial_fit(np.zeros((2, old.projector.n_known_)), np.zeros((2, 2)))


@pytest.mark.parametrize("meta_edit, arrays_edit, message", [
    (lambda m: [m], None, "format 'list'"),
    (lambda m: {k: v for k, v in m.items() if k != "feature_spec"}, None, "feature_spec"),
    (lambda m: {**m, "format_version": "two"}, None, "format version"),
    (lambda m: {**m, "format_version": 99}, None, "reads up to"),
    (lambda m: {**m, "training": [1]}, None, "training"),
    (None, lambda a: a.__setitem__("thresholds", np.zeros((3, 2))), "thresholds"),
    (None, lambda a: a.__setitem__("thresholds", np.full((2, 2), np.nan)), "thresholds"),
    (None, lambda a: a.__setitem__("projector.coef_",
                                   np.full_like(a["projector.coef_"], np.nan)), "finite"),
    (None, lambda a: a.pop("projector.coef_"), "coef_"),
    (None, lambda a: a.__setitem__("projector.n_components_", np.asarray(1.5)), "integer"),
])
def test_malformed_policy_files_are_one_line_errors(policy, tmp_path, meta_edit, arrays_edit,
                                                     message):
    path = policy.save(tmp_path / "p.npz")
    bad = _rewrite(path, tmp_path / "bad.npz", meta_edit, arrays_edit)
    with pytest.raises(PolicyFileError, match=message) as e:
        SfMPolicy.load(bad)
    assert "\n" not in str(e.value) and "bad.npz" in str(e.value)


@pytest.mark.parametrize("edit, message", [
    (lambda m: {**m, "projector": {**m["projector"], "magic": 1}}, "unknown projector parameter"),
    (lambda m: {**m, "n_components": "3"}, "n_components must be an integer"),
    (lambda m: {**m, "projector": [1, 2]}, "projector must be a JSON object"),
])
def test_malformed_format_1_files_are_one_line_errors(policy, tmp_path, edit, message):
    path = policy.save(tmp_path / "p.npz")
    bad = _rewrite(path, tmp_path / "bad.npz", lambda m: edit({**m, "format_version": 1}),
                   _to_version_1)
    with pytest.raises(PolicyFileError, match=message):
        SfMPolicy.load(bad)


def test_fit_stacks_datasets_with_the_same_layout(small_train):
    p = fit_policy([small_train, small_train], FeatureSpec(obs_names=small_train.sensor_names))
    assert p.training["rows"] == 2 * small_train.n_steps and p.training["episodes"] == 6


def test_onehot_policy_decodes_by_argmax(small_train, tmp_path):
    p = fit_policy(small_train, encoding="onehot")
    assert p.encoding == "onehot" and p.projector.n_missing_ == 6
    back = SfMPolicy.load(p.save(tmp_path / "oh.npz"))
    v = np.array([[0.1, 0.9, 0.0, 0.7, 0.2, 0.1]])
    assert back.decode(v).tolist() == [[1, 0]]


# ---------------------------------------------------------------- seeded science
@pytest.fixture(scope="module")
def wander_policy(wander_train):
    return fit_policy(wander_train)


def test_held_out_agreement_in_both_replay_modes(wander_policy, wander_held):
    """Seeded regression of the honest Figure 3 numbers (20 training episodes, seeds 0..19;
    held-out seeds 500..502). Teacher-forced, the policy looks good; free-running (how it
    drives) it does not beat the copy-previous or constant baselines on steer timing."""
    c = compare(wander_policy, wander_held)
    tf, fr = c.modes["teacher_forced"], c.modes["free_running"]
    cp, co = c.baselines["copy_previous"], c.baselines["constant"]
    measured = [  # at the time of writing
        ("teacher-forced", tf, "drive", 0.9717), ("teacher-forced", tf, "steer_timing", 0.9156),
        ("free-running", fr, "drive", 0.9367), ("free-running", fr, "steer_timing", 0.6822),
        ("free-running", fr, "onset_hit_w2", 0.7164),
        ("copy previous", cp, "steer_timing", 0.9261), ("constant", co, "steer_timing", 0.6928),
    ]
    for name, m, key, value in measured:
        assert abs(m[key] - value) < 0.01, (name, key, m[key], value)
    assert tf["steer_timing"] > fr["steer_timing"] + 0.15  # the replay mode matters this much
    assert fr["drive"] > co["drive"] + 0.2
    assert tf["onsets"] == fr["onsets"] == 67


def test_closed_loop_escape_rate_is_at_least_90_percent_of_the_teachers(wander_policy):
    teacher = evaluate("MKVJam-v0", "teacher", 50, 1000).metrics["escape_rate"]
    sfm = evaluate("MKVJam-v0", wander_policy, 50, 1000).metrics["escape_rate"]
    assert sfm >= 0.9 * teacher, (sfm, teacher)


def test_a_policy_that_sees_nothing_useful_fails_the_escape_target(wander_train):
    """The closed-loop test can fail: a policy fitted on the compass and battery only."""
    spec = FeatureSpec(obs_names=wander_train.sensor_names, channels=("compass", "battery"))
    blind = fit_policy(wander_train, spec)
    teacher = evaluate("MKVJam-v0", "teacher", 30, 1000).metrics["escape_rate"]
    assert evaluate("MKVJam-v0", blind, 30, 1000).metrics["escape_rate"] < 0.9 * teacher


# ---------------------------------------------------------------- rare channels
@given(n=st.integers(1, 200), active=st.integers(0, 200), min_support=st.integers(0, 50))
def test_rare_channels_counts_rows_away_from_the_mode(n, active, min_support):
    active = min(active, n // 2)              # the mode stays the resting value
    obs = np.zeros((n, 2))
    obs[:active, 0] = 1.0                     # a switch pressed in `active` rows
    obs[:, 1] = np.arange(n)                  # a counter: always varying
    rare = rare_channels(obs, ["bump", "ticks"], min_support)
    assert ("bump" in rare) == (active < min_support)
    if "bump" in rare:
        assert rare["bump"] == active
    assert ("ticks" in rare) == (n - 1 < min_support)


def test_a_rarely_pressed_bumper_is_held_constant_in_the_default_fit(small_train):
    # one row with the rear bumper pressed: with min_support 0 its features get coefficients
    # fitted to that one row (the failure: reversing into walls for good); the default preset
    # holds the channel and its traces constant, so their coefficients are exactly 0
    names = list(small_train.sensor_names)
    obs = np.array(small_train["observations"], copy=True)
    j = names.index("bump_rear")
    obs[:, j] = 0.0
    obs[len(obs) // 2, j] = 1.0
    data = build({**small_train.arrays, "observations": obs.astype(np.float32)},
                 small_train.metadata)
    spec, kw = preset("default", names)
    assert kw["min_support"] == 5
    held = fit_policy(data, spec, **kw)
    free = fit_policy(data, spec, **{**kw, "min_support": 0})
    cols = [i for i, f in enumerate(spec.feature_names) if f.startswith("bump_rear")]
    assert len(cols) == 3 and held.training["rare_channels"]["bump_rear"] == 1
    assert np.all(np.abs(held.projector.coef_[cols]) < 1e-9)  # zero up to rounding
    assert np.any(np.abs(free.projector.coef_[cols]) > 1e-3)
    assert "bump_rear" not in free.training["rare_channels"]
    # paper preset: every channel, as the paper
    assert preset("paper", names)[1]["min_support"] == 0


def test_min_support_must_be_a_non_negative_integer(small_train):
    with pytest.raises(ValueError, match="min_support"):
        fit_policy(small_train, min_support=-1)


# ---------------------------------------------------------------- the fewest rows a fit takes
def test_min_fit_rows_is_one_more_than_the_stacked_columns(small_train):
    names = small_train.sensor_names
    for name, need in (("default", 35), ("paper", 13), ("ols", 35)):
        assert min_fit_rows(preset(name, names)[0]) == need
    assert min_fit_rows(default_feature_spec(names), "onehot") == 32 + 6 + 1
    with pytest.raises(ValueError, match="encoding"):
        min_fit_rows(default_feature_spec(names), "binary")


def test_fit_policy_refuses_a_dataset_below_the_minimum(tiny_data):
    """Below features + commands + 1 rows the trailing singular values are zero by
    construction (centred rows span one dimension fewer than their count) and the rank rule
    ranks the row count: refused before any work; at the minimum every value can be nonzero."""
    from mkv_env.dataset import load

    short, enough = load(tiny_data(34)), load(tiny_data(35))
    with pytest.raises(ValueError, match=r"^the training data has 34 rows; an SfM fit of 32 "
                                         r"features \+ 2 command columns needs at least 35"):
        fit_policy(short)
    p = fit_policy(enough)
    assert p.training["rows"] == 35 and p.projector.singular_values_.size == 34
    with pytest.raises(ValueError, match="needs at least 39"):
        fit_policy(enough, encoding="onehot")
