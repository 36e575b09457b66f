"""How well the scripted teacher drives: the numbers quoted in docs/recorder.md.

* ``MKVJam-v0``: escape rate and mean time to escape over ``--jam-episodes`` (200) seeded
  episodes, per jam scenario (target: escapes in >= 95%).
* ``MKV-v0``: stuck fraction, distance and jams per minute over ``--episodes`` (100) episodes.

    python benchmarks/teacher_quality.py [--jam-episodes 200] [--episodes 100] [--policy teacher]
"""

from __future__ import annotations

import argparse
import collections

import numpy as np

from sfm_learn.evaluation import aggregate, evaluate


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--jam-episodes", type=int, default=200)
    ap.add_argument("--episodes", type=int, default=100)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--policy", default="teacher")
    args = ap.parse_args()

    jam = evaluate("MKVJam-v0", args.policy, args.jam_episodes, args.seed)
    m = jam.metrics
    print(f"MKVJam-v0, {args.policy}, {jam.episodes} episodes (seeds {args.seed}.."
          f"{args.seed + jam.episodes - 1})")
    print(f"  escape rate {m['escape_rate']:.3f}, mean time to escape "
          f"{m['mean_escape_time_s']:.2f} s")
    by = collections.defaultdict(list)
    for r in jam.records:
        by[r.scenario].append(r)
    for name, recs in sorted(by.items()):
        a = aggregate(recs)
        print(f"  {name:<9} {len(recs):>4} episodes, escape rate {a['escape_rate']:.3f}, "
              f"mean time {a['mean_escape_time_s']:.2f} s")

    wander = evaluate("MKV-v0", args.policy, args.episodes, args.seed)
    m = wander.metrics
    minutes = sum(r.duration_s for r in wander.records) / 60.0
    jams_per_min = sum(r.jams for r in wander.records) / minutes
    escapes = sum(r.escapes for r in wander.records)
    jams = sum(r.jams for r in wander.records)
    print(f"MKV-v0, {args.policy}, {wander.episodes} episodes x "
          f"{wander.records[0].duration_s:.0f} s")
    print(f"  stuck fraction {m['stuck_fraction']:.3f}")
    print(f"  distance {m['distance_m']:.2f} m per episode "
          f"(sd {np.std([r.distance_m for r in wander.records]):.2f})")
    print(f"  jams per minute {jams_per_min:.2f} ({jams} jams, {escapes} escaped)")
    print(f"  collisions per minute {m['collisions_per_min']:.2f}")
    print(f"  mean return {m['mean_return']:.2f}")


if __name__ == "__main__":
    main()
