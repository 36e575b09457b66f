"""A 3-axis sensor with 4 or 5 channels on a one-reading log: one or two complement dimensions
do not identify each channel's variance (Ledermann's bound), and the printed interval takes
the noise level along the load's span from the fit's radial residuals
(:func:`calib.estimators.forward.shared_noise.range_level`). Seeds 13,000 on: never used while it
was developed (the development rigs 10,000-10,029 and 12,000-12,039 measured, without the level ->
with it: 4 channels 24 -> 29 of 30 and 28 -> 40 of 40 inside the 95 % interval, 5 channels 29 -> 29
and 36 -> 37)."""

import functools

import pytest

from calib import fit_least_squares


def _one(fit, seed, p):
    """``fit``: the ``payload_joint`` fixture. (held-out error, least squares' with every load
    known on the same readings, the predicted error with ``whitened``)."""
    f = fit(seed, p=p)
    ls = fit_least_squares(f.rig.Z[f.tr], f.M[f.tr], bias=True)
    j = f.cal.diagnostics["joint"]
    pe = dict(j["predicted_error"], whitened=bool(j["noise_correlation"].get("used")))
    return f.err, f.rms(ls), pe


@functools.cache
def _rigs(fit, p):
    """The 20 rigs of ``p`` channels the tests below share (seeds 13,000-13,019)."""
    return tuple(_one(fit, 13_000 + k, p) for k in range(20))


@pytest.mark.parametrize("p", [4, 5])
def test_the_interval_holds_where_the_variances_are_not_identified(p, payload_joint):
    res = _rigs(payload_joint, p)
    inside = [pe["interval"][0] <= e <= pe["interval"][1] for e, _, pe in res]
    # 95 % nominal: 17 of 20 or more (fewer has probability 1.6 % under it)
    assert sum(inside) >= 17, sum(inside)
    # (a fit refitted in whitened channels, noise found shared, weighs its range by the shared
    # part's own model instead: 1 of the 5-channel rigs here)
    assert all(pe["range_level"] is not None and pe["range_level"]["dof"] >= 5
               for _, _, pe in res if not pe["whitened"])
    assert sum(pe["whitened"] for _, _, pe in res) <= 2
    assert max(e / ls for e, ls, _ in res) < 3.0


def test_the_radial_level_is_what_brings_the_four_channel_interval_to_its_rate(monkeypatch,
                                                                               payload_joint):
    """The same 20 four-channel rigs with the level left out (the interval as it was without
    it): fewer inside, the misses below the interval (its noise too high: 17 of 20 then, 3
    below; 20 of 20 with it), so the coverage above is the level's doing. The rigs without the
    level are fitted in order and the test stops once the rigs left cannot change its outcome
    (the verdict is that of all 20)."""
    import calib.verdict.predicted_error

    with_level = _rigs(payload_joint, 4)
    inside_with = sum(pe["interval"][0] <= e <= pe["interval"][1] for e, _, pe in with_level)
    need_out = len(with_level) + 2 - inside_with  # misses without the level, at least
    monkeypatch.setattr(calib.verdict.predicted_error, "range_level", lambda pr, fit: None)
    out = below = 0
    for k in range(20):
        e, _, pe = _one(payload_joint, 13_000 + k, 4)
        assert pe["range_level"] is None
        out += not pe["interval"][0] <= e <= pe["interval"][1]
        below += e < pe["interval"][0]
        left = 19 - k
        if below >= 2 and out >= need_out:
            break  # certain to pass
        if below + left < 2 or out + left < need_out:
            break  # certain to fail
    assert out >= need_out, (inside_with, out, k + 1)
    assert below >= 2, (below, k + 1)


def test_identified_variances_leave_the_interval_as_it_was(payload_joint):
    """Six channels or more identify the variances: no radial level is drawn (the payload
    study's rows, all p >= 6, are unchanged by it)."""
    _, _, pe = _one(payload_joint, 13_100, 8)
    assert pe["range_level"] is None
