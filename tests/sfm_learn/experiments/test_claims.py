"""sfm_learn.experiments.claims: failure rates, paired verdicts, the README's generated claims."""

import functools
import json
import os
import pathlib
import re

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sfm_learn.experiments import claims


@functools.lru_cache(maxsize=1)
def _bundled_block() -> str:
    """The README block of the bundled rows, computed once (its bootstraps take seconds)."""
    return claims.readme_block(claims.load_reference())


def _row(learner, budget, seed, escape=None, distance=None, status="ok", escaped=None):
    m = {}
    if escape is not None:
        m["MKVJam-v1"] = {"escape_rate": escape}
    if distance is not None:
        m["MKV-v1"] = {"distance_m": distance}
    row = {"learner": learner, "budget": budget, "seed": seed, "status": status, "metrics": m}
    if escaped is not None:  # per-episode outcomes on banks of equal size
        m["MKVJam-v1"] = {"escape_rate": float(np.mean(escaped))}
        row["episodes"] = {"MKVJam-v1": {"bank": [i * 2 // len(escaped) for i in
                                                  range(len(escaped))],
                                         "escaped": [int(e) for e in escaped],
                                         "distance_m": [1.0] * len(escaped)}}
    return row


def test_failure_counts_either_test_where_measured():
    rows = [_row("bc", 1200, 0, 0.95, 14.0), _row("bc", 1200, 1, 0.70, 14.0),
            _row("bc", 1200, 2, 0.95, 6.0), _row("bc", 1200, 3, 0.79, 9.0),
            _row("bc", 1200, 4, 0.2, 0.0, status="error"),  # error rows are not averaged
            _row("ppo-jam", 200000, 0, 0.5), _row("ppo-wander", 200000, 0, distance=12.0)]
    pts = claims.by_point(rows)
    p = claims.point_summary(pts[("bc", 1200)])
    assert p["n"] == 4 and p["failures"] == 3
    assert np.isclose(p["escape_mean"], np.mean([0.95, 0.70, 0.95, 0.79]))
    assert claims.point_summary(pts[("ppo-jam", 200000)])["failures"] == 1
    wander = claims.point_summary(pts[("ppo-wander", 200000)])
    assert wander["failures"] == 0 and "escape_mean" not in wander


def test_a_consistent_gap_is_ranked_and_noise_is_not():
    rng = np.random.default_rng(3)
    base = rng.uniform(0.85, 0.95, 20)
    rows = [_row("sfm", 1200, s, base[s] + 0.05, 14) for s in range(20)]
    rows += [_row("bc", 1200, s, base[s], 14) for s in range(20)]
    # dagger: the same as sfm plus zero-mean noise much larger than any paired effect
    noise = rng.normal(0, 0.05, 20)
    noise -= noise.mean()
    rows += [_row("dagger", 1200, s, base[s] + 0.05 + noise[s], 14) for s in range(20)]
    pts = claims.by_point(rows)
    assert claims.paired(pts, "sfm", "bc", 1200)["verdict"] == "sfm"
    assert claims.paired(pts, "bc", "sfm", 1200)["verdict"] == "sfm"
    assert claims.paired(pts, "sfm", "dagger", 1200)["verdict"] is None
    text = " ".join(claims.claim_sentences(rows))
    assert "SfM above BC" in text and "SfM and DAgger: no clear difference" in text


def test_too_few_common_sets_give_no_verdict():
    rows = [_row("sfm", 1200, s, 1.0, 14) for s in range(3)]
    rows += [_row("bc", 1200, s, 0.5, 14) for s in range(3)]
    r = claims.paired(claims.by_point(rows), "sfm", "bc", 1200)
    assert r["n"] == 3 and r["verdict"] is None and r["mean"] == 0.5
    assert "too few" in claims.tables(rows) and "too few common sets" in \
        claims.claim_sentences(rows)[0]


@settings(max_examples=40, deadline=None)
@given(diffs=st.lists(st.floats(-0.5, 0.5, allow_nan=False), min_size=10, max_size=30))
def test_the_verdict_names_a_learner_exactly_when_the_interval_excludes_zero(diffs):
    rows = [_row("sfm", 1200, s, 0.5 + d, 14) for s, d in enumerate(diffs)]
    rows += [_row("bc", 1200, s, 0.5, 14) for s in range(len(diffs))]
    r = claims.paired(claims.by_point(rows), "sfm", "bc", 1200)
    lo, hi = r["ci"]
    assert lo <= r["mean"] + 1e-12 and r["mean"] <= hi + 1e-12
    assert r["verdict"] == ("sfm" if lo > 0 else "bc" if hi < 0 else None)


def test_with_episodes_the_interval_covers_them_and_is_wider_than_sets_only():
    """Per-episode rows: the level's interval resamples episodes too (hard and easy episodes
    shared by every set), so it is wider than the interval over the same sets' rates alone."""
    rng = np.random.default_rng(0)
    easy = rng.random(40) < 0.8  # shared episode difficulty: most easy, some hard
    rows, rates = [], []
    for s in range(20):
        esc = np.where(easy, rng.random(40) < 0.98, rng.random(40) < 0.3)
        rows.append(_row("sfm", 1200, s, escaped=esc))
        rates.append(_row("sfm", 1200, s, float(esc.mean())))
    with_eps = claims.point_summary(claims.by_point(rows)[("sfm", 1200)])
    sets_only = claims.point_summary(claims.by_point(rates)[("sfm", 1200)])
    assert with_eps["covers"].startswith("training sets and evaluation episodes (40 in 2 banks")
    assert sets_only["covers"] == "training sets (the evaluation episodes held fixed)"
    assert with_eps["escape_mean"] == pytest.approx(sets_only["escape_mean"])
    w = with_eps["escape_ci"][1] - with_eps["escape_ci"][0]
    assert w > 1.5 * (sets_only["escape_ci"][1] - sets_only["escape_ci"][0])
    assert "over training sets and evaluation episodes" in claims.claim_sentences(rows)[0]


def test_a_distance_interval_covers_episodes_too():
    """A wander learner's distances per episode: its level's interval resamples the shared
    episodes (some short for every set), wider than over the sets' means alone, and the PPO
    sentence says what it covers."""
    rng = np.random.default_rng(1)
    length = np.where(rng.random(40) < 0.8, 15.0, 5.0)  # shared episode difficulty
    rows, means = [], []
    for s in range(10):
        d = length + rng.normal(0, 0.3, 40)
        row = _row("ppo-wander", 200000, s, distance=float(d.mean()))
        row["episodes"] = {"MKV-v1": {"bank": [i // 20 for i in range(40)], "escaped": None,
                                      "distance_m": d.tolist()}}
        rows.append(row)
        means.append(_row("ppo-wander", 200000, s, distance=float(d.mean())))
    with_eps = claims.point_summary(claims.by_point(rows)[("ppo-wander", 200000)])
    sets_only = claims.point_summary(claims.by_point(means)[("ppo-wander", 200000)])
    assert with_eps["distance_mean"] == pytest.approx(sets_only["distance_mean"])
    assert with_eps["distance_covers"].startswith("training sets and evaluation episodes (40 in")
    lo, hi = with_eps["distance_ci"]
    assert lo < with_eps["distance_mean"] < hi
    assert hi - lo > 3 * (sets_only["distance_ci"][1] - sets_only["distance_ci"][0])
    text = claims.claim_sentences(rows)[0]
    assert text.startswith("PPO (wander reward) (mean [95 % bootstrap interval over PPO seeds "
                           "and evaluation episodes (40 in 2 banks)] (where a rerun lands: 10 new "
                           "PPO seeds on a new bank of 20 episodes per env, 95 %)): at 200k env "
                           "steps it wanders")


def test_a_check_sweep_is_compared_level_by_level_and_verdict_by_verdict():
    """A check sweep from the same learners covers the published levels; a learner whose
    check is far off is flagged, and a published ranking the check turns around is reversed."""
    rng = np.random.default_rng(5)

    def sweep(seeds, sfm_shift, bc_level):
        rows = []
        for s in seeds:
            base = rng.uniform(0.85, 0.9)
            rows.append(_row("sfm", 1200, s, base + sfm_shift, 14 + rng.normal(0, 0.1)))
            rows.append(_row("bc", 1200, s, bc_level + rng.normal(0, 0.01), 14.0))
        return rows

    published = sweep(range(20), 0.05, 0.85)
    same = claims.check(published, sweep(range(100, 120), 0.05, 0.85))
    assert [q["learner"] for q in same["levels"]].count("sfm") == 2  # escape and distance
    assert all(q["covered"] for q in same["levels"] if q["metric"] == "distance")
    (pair,) = same["pairs"]
    assert pair["verdict"] == "sfm" and pair["held"] and not pair["reversed"]
    turned = claims.check(published, sweep(range(100, 120), -0.08, 0.95))
    (pair,) = turned["pairs"]
    assert pair["reversed"] and pair["flipped"] and pair["check_verdict"] == "bc"
    assert not all(q["covered"] for q in turned["levels"] if q["metric"] == "escape")
    text = claims.check_report(turned)
    assert "**reversed**" in text and "**no**" in text and "reversed 1" in text


def test_each_bank_held_out_is_judged_by_the_other_banks():
    """Rows on 3 banks: every (point, metric, bank) gets an interval from the other two banks
    and the held-out bank's own mean; a bank whose episodes are much harder than the others'
    falls outside both intervals, and the tables say how many levels were covered."""
    rng = np.random.default_rng(4)
    rows = []
    for s in range(12):
        p = np.r_[np.full(40, 0.95), np.full(40, 0.95), np.full(40, 0.5)]  # bank 2 is hard
        esc = (rng.random(120) < p).astype(int)
        row = _row("sfm", 1200, s, escape=float(esc.mean()), distance=14.0)
        row["episodes"] = {"MKVJam-v1": {"bank": [i // 40 for i in range(120)],
                                         "escaped": esc.tolist(), "distance_m": [1.0] * 120}}
        rows.append(row)
    held = claims.held_out_banks(rows)
    assert [(q["metric"], q["bank"]) for q in held] == [("escape", 0), ("escape", 1),
                                                         ("escape", 2)]
    hard = held[2]
    assert hard["value"] < 0.6 and not hard["covered"] and not hard["in_replication"]
    assert held[0]["replication"][0] <= held[0]["ci"][0] and held[0]["ci"][1] <= (
        held[0]["replication"][1])
    assert "escape levels in the 95 % CI" in claims.tables(rows)


def test_a_table_is_one_holm_family():
    """Three comparisons near the edge: each alone would rank at 95 %, Holm ranks fewer."""
    rng = np.random.default_rng(11)
    base = rng.uniform(0.8, 0.9, 20)
    rows = [_row("sfm", 1200, s, base[s], 14) for s in range(20)]
    for name, shift in (("bc", 0.012), ("dagger", 0.011), ("sfm-ols", 0.010)):
        noise = rng.normal(0, 0.02, 20)
        rows += [_row(name, 1200, s, base[s] - shift + noise[s], 14) for s in range(20)]
    t = claims.budget_table(claims.by_point(rows), 1200)
    for r in t.values():
        assert r["confidence"] >= 0.95 and r["ci"][0] <= r["mean"] <= r["ci"][1]
        assert (r["verdict"] is not None) == (r["p_adjusted"] < 0.05 and r["n"] >= 10)
    assert "Holm-adjusted p" in claims.tables(rows)


@pytest.mark.parametrize("page", ["README.md", "docs/baselines.md"])
def test_the_docs_claims_are_the_generated_sentences_of_the_bundled_rows(page):
    # every ranking sentence of the claims paragraphs is generated from the bundled rows
    text = (pathlib.Path(__file__).resolve().parents[3] / page).read_text()
    block = re.search(r"<!-- claims:begin -->\n(.*?)\n<!-- claims:end -->", text, re.S)
    assert block, f"{page} has no generated claims block"
    expected = _bundled_block()
    assert block.group(1).strip() == expected.strip(), (
        f"{page}'s claims differ from the bundled rows: regenerate with "
        f"python -m sfm_learn.experiments.claims --write {page}")


def test_the_bundle_says_which_sweep_ran_on_which_banks():
    doc = claims.load_reference()
    banks = {s.get("name"): s["eval"].get("banks", 1) for s in doc["specs"]}
    head = _bundled_block().split("\n\n")[0].replace("\n", " ")
    assert max(banks.values()) >= 3  # the published teacher-step claims: three banks
    for spec in doc["specs"]:
        assert f"`{spec['name']}` on " in head or len({json.dumps(s["eval"]) for s in
                                                       doc["specs"]}) == 1
    rows = [r for r in doc["rows"] if r["learner"] == "sfm"]
    assert rows and all(len(set(r["episodes"]["MKVJam-v1"]["bank"])) == 3 for r in rows)


def test_replace_block_swaps_only_the_marked_part():
    text = "a\n<!-- claims:begin -->\nold\n<!-- claims:end -->\nb\n"
    assert claims.replace_block(text, "new\n") == (
        "a\n<!-- claims:begin -->\nnew\n<!-- claims:end -->\nb\n")
    with pytest.raises(ValueError, match="no <!-- claims:begin"):
        claims.replace_block("nothing here", "x")


def _summary_script():
    import importlib.util

    path = pathlib.Path(__file__).resolve().parents[3] / "scripts" / "claims_summary.py"
    spec = importlib.util.spec_from_file_location("claims_summary", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _sweep_dir(root, rows):
    (root / "rows").mkdir(parents=True)
    (root / "spec.json").write_text(json.dumps({"name": root.name, "eval": {"episodes": 2,
                                                                             "seed": 1}}))
    for k, r in enumerate(rows):
        (root / "rows" / f"r{k}.json").write_text(json.dumps(r))


def test_the_summary_script_checks_a_sweep_and_refuses_bad_folders(tmp_path, capsys):
    mod = _summary_script()
    rng = np.random.default_rng(0)
    for name in ("pub", "chk"):
        _sweep_dir(tmp_path / name, [_row(lr, 1200, s, float(rng.uniform(0.85, 0.95)), 14.0)
                                     for lr in ("sfm", "bc") for s in range(12)])
    assert mod.main([str(tmp_path / "pub"), "--check", str(tmp_path / "chk")]) == 0
    out = capsys.readouterr().out
    assert "Levels covered:" in out and "| sfm - bc | 1,200 |" in out
    with pytest.raises(SystemExit) as e:
        mod.main([str(tmp_path / "pub"), "--check", str(tmp_path / "missing")])
    assert "has no rows/ folder" in str(e.value) and "\n" not in str(e.value)
    with pytest.raises(SystemExit):
        mod.main([])  # neither SWEEP_DIR nor --bundled: a usage error
    with pytest.raises(SystemExit):
        mod.main(["--bundled", "--bundle", str(tmp_path / "x.json")])
    assert not (tmp_path / "x.json").exists()
    # a FIFO, a broken file and a row with NaN metrics are left out by name, never read or hung on
    os.mkfifo(tmp_path / "chk" / "rows" / "fifo.json")
    (tmp_path / "chk" / "rows" / "broken.json").write_text("{")
    bad = _row("sfm", 1200, 99, 0.9, 14.0)
    bad["metrics"]["MKVJam-v1"]["escape_rate"] = float("nan")
    (tmp_path / "chk" / "rows" / "nan.json").write_text(json.dumps(bad))
    assert len(mod.read_rows(str(tmp_path / "chk"))) == 24
    err = capsys.readouterr().err
    assert all(f"{n}.json left out" in err for n in ("fifo", "broken", "nan"))
    (tmp_path / "pub" / "spec.json").write_text("[1]")
    with pytest.raises(SystemExit, match="not a sweep spec"):
        mod.main([str(tmp_path / "pub")])
