"""A bad-input campaign through the ``mkv`` and ``calib`` commands, counting outcomes.

    .venv/bin/python scripts/fuzz_cli.py [--cases 500] [--seed 0]

Every case runs the command in this process and records: exit status 0 (accepted), 2 (refused
with one line), anything else; an exception escaping ``main`` (a traceback); stderr lines beyond
one; and whether any input file changed or an output appeared on a refusal. Categories: random,
truncated and damaged files (datasets, policies, CAL.json, CSV), out-of-range numbers, malformed
``--env-kwargs``, and outputs colliding with inputs; and the surfaces added since: sweep specs
(random field values, infinities, deep nesting), sweep folders (damaged rows, ``--plot`` onto the
sweep's files), FIFOs given as any file a command reads (a case that blocks for 20 s counts as a
hang), ``sb3:`` zips and ``vecnormalize.pkl`` files carrying payloads that would create a marker
file if unpickled (``code execution``), Minari ids, and CSV headers. ``--interrupts N`` adds N
Ctrl-C cases: a long command in a subprocess sent SIGINT, to its process group or its
main process alone, at a random 0.3-6 s (imports, worker start-up, work); it must print one line,
exit 130, write nothing and leave no process. Library warnings before a one-line error count as
a multi-line error (Python's default warning filters: what a user sees). The counts go into the
issue notes.
"""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import io
import json
import math
import os
import random
import shutil
import signal
import sys
import tempfile
from collections import Counter


class _Hang(Exception):
    pass


def _alarm(signum, frame):
    raise _Hang()


class Payload:
    """Unpickling this creates the file ``path`` (stands for any code a payload would run)."""

    def __init__(self, path):
        self.path = path

    def __reduce__(self):
        return (open, (self.path, "w"))


def snapshot(d):
    return {p: hashlib.sha256(open(os.path.join(d, p), "rb").read()).hexdigest()
            for p in sorted(os.listdir(d)) if os.path.isfile(os.path.join(d, p))}


def run(main, argv):
    err = io.StringIO()
    signal.signal(signal.SIGALRM, _alarm)
    signal.alarm(20)
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            code = main([str(a) for a in argv])
    except _Hang:
        return "hang", " ".join(map(str, argv))
    except BaseException as e:  # noqa: BLE001  (what we count)
        return "traceback", f"{type(e).__name__}: {e}"
    finally:
        signal.alarm(0)
    text = err.getvalue()
    if code not in (0, 2, 130):
        return f"exit {code}", text
    if code == 2 and text.count("\n") != 1:
        return "multi-line error", text
    return ("accepted" if code == 0 else "refused"), text


INTERRUPT_SIGINT = "import signal, sys; signal.signal(signal.SIGINT, signal.default_int_handler)"


def interrupt_case(rng, d):
    """One long command started in its own session and sent SIGINT (to its process group, as a
    terminal's Ctrl-C, or to the main process alone) after a random 0.3-6 s: the outcome is
    "interrupted" (one line, exit 130, no output, no process left), "finished" (it ended first)
    or what went wrong."""
    import subprocess
    import time

    import psutil

    # the console scripts' own launchers: a Ctrl-C during the packages' imports counts too
    mkv = f"{INTERRUPT_SIGINT}; from mkv_sfm_launch import mkv; sys.exit(mkv())"
    calib = f"{INTERRUPT_SIGINT}; from mkv_sfm_launch import calib; sys.exit(calib())"
    out = os.path.join(d, "int_out")
    shutil.rmtree(out, ignore_errors=True)
    for leftover in (out, out + ".npz", out + ".zip", out + ".json"):  # an earlier case's output
        with contextlib.suppress(FileNotFoundError):
            os.unlink(leftover)
    prog, argv = rng.choice([
        (mkv, ["eval", "--env", "MKVJam-v1", "--policy", "teacher", "--episodes", "5000",
               "--workers", "2", "--json", out]),
        (mkv, ["record", "--env", "MKV-v1", "--policy", "teacher", "--episodes", "500",
               "--out", out + ".npz"]),
        (mkv, ["train-ppo", "--env", "MKV-v0", "--timesteps", "200000", "--out", out + ".zip"]),
        (mkv, ["train-bc", os.path.join(d, "data.npz"), "--epochs", "100000", "--out",
               out + ".zip"]),
        (mkv, ["train-dagger", "--env", "MKV-v1", "--steps", "100000", "--out", out + ".zip"]),
        (mkv, ["sweep", os.path.join(d, "spec.json"), "--out", out, "--workers", "2"]),
        (mkv, ["demo", "--out", out]),
        (calib, ["trials", "--out", out, "--seeds", "50000", "--no-plots"]),
        (calib, ["fit", os.path.join(d, "raw.csv"), "--dof", "3", "--bias", "--bootstrap",
                 "100000", "--out", out + ".json"]),
    ])
    to = rng.choice(["group", "main"])
    delay = rng.uniform(0.3, 6.0)
    proc = subprocess.Popen([sys.executable, "-c", prog, *argv], stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True, start_new_session=True,
                            env=dict(os.environ, SDL_VIDEODRIVER="dummy"))
    time.sleep(delay)
    children = []
    with contextlib.suppress(psutil.NoSuchProcess):
        children = psutil.Process(proc.pid).children(recursive=True)
    if proc.poll() is not None:
        return "finished", argv
    (os.killpg if to == "group" else os.kill)(proc.pid, signal.SIGINT)
    try:
        _, err = proc.communicate(timeout=60)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        return "hang", argv
    _, alive = psutil.wait_procs(children, timeout=15)
    left = [p for p in (out, out + ".npz", out + ".zip", out + ".json") if os.path.exists(p)]
    if "Traceback" in err:
        return "traceback", (argv, to, delay, err[-300:])
    if proc.returncode == 0:
        return "finished", argv
    if proc.returncode != 130 or err.count("\n") != 1:
        return "multi-line error", (argv, to, delay, proc.returncode, err[-300:])
    if alive:
        return "process left", (argv, to, delay)
    if left and "sweep" not in argv:  # a sweep keeps its finished rows by design (it resumes)
        return "partial output", (argv, to, delay, left)
    return "interrupted", None


def main_() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=500, help="bad-input cases (in this process)")
    ap.add_argument("--interrupts", type=int, default=0,
                    help="also this many Ctrl-C cases: a long command in a subprocess sent "
                    "SIGINT (group or main process) at a random moment")
    ap.add_argument("--seed", type=int, default=0, help="random seed of the campaign")
    args = ap.parse_args()
    os.environ.setdefault("SDL_VIDEODRIVER", "dummy")
    os.environ.setdefault("MPLBACKEND", "Agg")
    os.environ["MINARI_DATASETS_PATH"] = tempfile.mkdtemp(prefix="mkv-fuzz-minari-")
    import numpy as np

    from calib.cli import main as calib
    from calib.data.io import write_csv
    from calib.simulation.simulate import paper_trial
    from mkv_env.dataset import save
    from mkv_env.recorder import record
    from sfm_learn.cli import main as mkv
    from sfm_learn.eigenspace.policy import fit_policy

    rng = random.Random(args.seed)
    d = tempfile.mkdtemp(prefix="mkv-fuzz-")
    data = record("MKV-v0", "teacher", 2, 0, {"max_episode_steps": 60})
    save(data, os.path.join(d, "data.npz"))
    fit_policy(data).save(os.path.join(d, "policy.npz"))
    write_csv(os.path.join(d, "raw.csv"), [f"g{i}" for i in range(8)], paper_trial(2, rng=0).Z)
    assert calib(["fit", os.path.join(d, "raw.csv"), "--dof", "3", "--magnitude", "9",
                  "--out", os.path.join(d, "cal.json")]) == 0
    trial = paper_trial(2, rng=0)
    write_csv(os.path.join(d, "loads.csv"), [f"g{i}" for i in range(8)] + ["Fx", "Fy", "Fz"],
              np.hstack([trial.Z, trial.loads]))
    write_csv(os.path.join(d, "poses.csv"), ["Fx", "Fy", "Fz"], trial.directions[:12])
    import base64
    import pickle
    import zipfile

    import gymnasium as gym
    from stable_baselines3 import PPO

    PPO("MlpPolicy", gym.make("MKV-v0"), n_steps=32, batch_size=32, device="cpu",
        policy_kwargs={"net_arch": [8]}).save(os.path.join(d, "ppo.zip"))
    with open(os.path.join(d, "spec.json"), "w") as f:
        json.dump({"name": "fz", "env": ["MKVJam-v1"], "eval": {"episodes": 1, "seed": 9},
                   "seeds": [0], "learners": {"sfm": {}}, "budgets": {"sfm": [1200]}}, f)
    sweep_dir = os.path.join(d, "sweepdir")
    assert mkv(["sweep", os.path.join(d, "spec.json"), "--out", sweep_dir, "--quiet"]) == 0
    marker = os.path.join(d, "PWNED")
    originals = {n: open(os.path.join(d, n), "rb").read() for n in os.listdir(d)
                 if os.path.isfile(os.path.join(d, n))}
    odd = ["-1", "0", "nan", "inf", "1e20", "99999999999999999999999", "abc", "", "2.5",
           "-0", "1e-300", "0x10"]
    odd_json = [-1, 0, math.nan, math.inf, 1e300, "x", None, [1], {}, True, -1e-9]

    def damaged(name):
        raw = bytearray(originals[name])
        kind = rng.choice(["random", "truncate", "flip", "empty"])
        if kind == "random":
            return bytes(rng.getrandbits(8) for _ in range(rng.randint(1, 600)))
        if kind == "truncate":
            return bytes(raw[:rng.randint(0, len(raw) - 1)])
        if kind == "flip":
            for _ in range(rng.randint(1, 20)):
                i = rng.randrange(len(raw))
                raw[i] = rng.getrandbits(8)
            return bytes(raw)
        return b""

    def case():
        """(main, argv, inputs) for one random bad-input case."""
        p = lambda n: os.path.join(d, n)  # noqa: E731
        cat = rng.choice(["file", "number", "kwargs", "collision", "csv", "caljson", "sweep",
                          "sweepdir", "fifo", "payload", "minari", "header"])
        if cat == "sweep":
            spec = json.loads(originals["spec.json"])
            field = rng.choice(["name", "env", "teacher_env", "eval", "seeds", "learners",
                                "budgets"])
            spec[field] = rng.choice(odd_json + [[math.inf], {"..": {}}, {"bc": {"epochs": -1}},
                                                 {"sfm": [math.inf]}, ["CartPole-v1"]])
            text = json.dumps(spec) if rng.random() < 0.8 else "[" * 100_000
            name = "s.yml" if rng.random() < 0.3 else "s.json"
            with open(p(name), "w") as f:
                f.write(text.replace("Infinity", ".inf") if name.endswith(".yml") else text)
            return cat, (mkv, ["sweep", p(name), "--out", p("sout")])
        if cat == "sweepdir":
            dd = p("sw2")
            shutil.rmtree(dd, ignore_errors=True)
            shutil.copytree(sweep_dir, dd)
            rows = os.path.join(dd, "rows")
            row = os.path.join(rows, sorted(os.listdir(rows))[0])
            bad = rng.choice([b'{"metrics": "abc", "status": "ok"}', b"[1]", b"{",
                              b'{"learner": "sfm", "seed": 0, "budget": 60, "status": "ok"}'])
            with open(os.path.join(rows, "sfm__s7__b60.json"), "wb") as f:
                f.write(bad)
            plot = rng.choice([os.path.join(dd, "spec.json"), row, p("spec.json"),
                               p("c.png")])
            return cat, (mkv, ["sweep", "--summary", dd, "--plot", plot])
        if cat == "fifo":
            fifo = p("fifo")
            with contextlib.suppress(FileNotFoundError):
                os.unlink(fifo)
            os.mkfifo(fifo)
            return cat, rng.choice([
                (mkv, ["eval", "--env", "MKV-v0", "--policy", f"sb3:PPO:{fifo}", "--episodes",
                       "1"]),
                (mkv, ["eval", "--env", "MKV-v0", "--policy", f"script:{fifo}", "--episodes",
                       "1"]),
                (mkv, ["sweep", fifo, "--out", p("sout")]),
                (mkv, ["train-ppo", "--env", "MKV-v1", "--hyperparams", fifo, "--timesteps",
                       "64", "--out", p("o.zip")]),
                (calib, ["apply", fifo, p("raw.csv"), "--out", p("o.csv")]),
                (calib, ["fit", fifo, "--dof", "3", "--out", p("o.json")]),
            ])
        if cat == "payload":
            payload = base64.b64encode(pickle.dumps(Payload(marker))).decode()
            run_dir = p("run")
            shutil.rmtree(run_dir, ignore_errors=True)
            os.makedirs(os.path.join(run_dir, "ppo"))
            zpath = os.path.join(run_dir, "ppo.zip")
            where = rng.choice(["data", "beside", "zoo", "other"])
            with zipfile.ZipFile(p("ppo.zip")) as zin, zipfile.ZipFile(zpath, "w") as zout:
                for item in zin.infolist():
                    raw = zin.read(item.filename)
                    if item.filename == "data" and where == "data":
                        doc = json.loads(raw)
                        key = rng.choice(["extra", "policy_class", "observation_space",
                                          "action_space", "policy_kwargs", "lr_schedule"])
                        entry = dict(doc.get(key) or {}) if isinstance(doc.get(key), dict) \
                            else {}
                        entry[":serialized:"] = payload
                        doc[key] = entry
                        raw = json.dumps(doc).encode()
                    zout.writestr(item, raw)
            pkl = {"beside": os.path.join(run_dir, "vecnormalize.pkl"),
                   "zoo": os.path.join(run_dir, "ppo", "vecnormalize.pkl"),
                   "other": os.path.join(run_dir, "other", "vecnormalize.pkl")}.get(where)
            if pkl is not None:
                os.makedirs(os.path.dirname(pkl), exist_ok=True)
                with open(pkl, "wb") as f:
                    pickle.dump(Payload(marker), f)
            extra = rng.choice([[], ["--policy", "bogus"], ["--workers", "2"]])
            return cat, (mkv, ["eval", "--env", "MKV-v0", "--policy", f"sb3:PPO:{zpath}",
                               "--episodes", "1", *extra])
        if cat == "minari":
            ident = rng.choice(["mkv/teacher-v0/inner-v0", "/".join(["a"] * 2000) + "/n-v0",
                                "", "..", "mkv/../x-v0", "x" * 500 + "/n-v0"])
            return cat, (mkv, ["export", p("data.npz"), "--minari", ident])
        if cat == "header":
            head = rng.choice([",,,,,,,", "1,2,3,4,5,6,7,8", "\ufeff,a,b,c,d,e,f,g",
                               "g0,g0,g2,g3,g4,g5,g6,g7", " , , , , , , , "])
            body = open(p("raw.csv")).read().split("\n", 1)[1]
            with open(p("h.csv"), "w", encoding="utf-8") as f:
                f.write(head + "\n" + body)
            return cat, (calib, ["fit", p("h.csv"), "--dof", "3", "--magnitude", "9", "--out",
                                 p("o.json")])
        if cat == "file":
            name = rng.choice(["data.npz", "policy.npz"])
            with open(p("bad_" + name), "wb") as f:
                f.write(damaged(name))
            bad = p("bad_" + name)
            return cat, rng.choice([
                (mkv, ["fit", bad, "--out", p("o.npz")]),
                (mkv, ["train-bc", bad, "--out", p("o.zip"), "--epochs", "1"]),
                (mkv, ["compare", bad if name == "data.npz" else p("data.npz"),
                       p("policy.npz") if name == "data.npz" else bad]),
                (mkv, ["eval", "--env", "MKVJam-v0", "--policy", f"sfm:{bad}", "--episodes",
                       "1"]),
                (mkv, ["record", "--env", "MKVJam-v0", "--policy", f"sfm:{bad}",
                       "--episodes", "1", "--out", p("o.npz")]),
            ])
        if cat == "number":
            v = rng.choice(odd)
            return cat, rng.choice([
                (mkv, ["record", "--env", "MKVJam-v0", "--policy", "random", "--episodes", v,
                       "--out", p("o.npz")]),
                (mkv, ["eval", "--env", "MKVJam-v0", "--policy", "random", "--episodes", "1",
                       "--seed", v]),
                (mkv, ["train-ppo", "--env", "MKVJam-v0", "--timesteps", v, "--out",
                       p("o.zip")]),
                (mkv, ["fit", p("data.npz"), "--out", p("o.npz"), "--history", v]),
                (mkv, ["fit", p("data.npz"), "--out", p("o.npz"), "--rank", v]),
                (calib, ["trials", "--seeds", v, "--out", p("tr")]),
                (calib, ["plan", p("poses.csv"), "--known-loads", v]),
                (calib, ["plan", p("poses.csv"), "--samples", v, "--noise", v,
                         "--sensitivity", "10"]),
                (calib, ["fit", p("loads.csv"), "--dof", "3", "--method", "least_squares",
                         "--cv", "poses", "--holdout-factor", v, "--out", p("o.json")]),
                (calib, ["fit", p("raw.csv"), "--dof", "3", "--magnitude", v, "--out",
                         p("o.json")]),
            ])
        if cat == "kwargs":
            group = rng.choice(["robot_params", "sensor_params", "env"])
            if group == "robot_params":
                field = rng.choice(["mass_kg", "tire_friction", "chassis_friction", "length_m",
                                    "steer_limit_rad", "drive_load_fraction",
                                    "drive_wheel_radius_m", "nope"])
                kw = {"robot_params": {field: rng.choice(odd_json)}}
            elif group == "sensor_params":
                kw = {"sensor_params": rng.choice(
                    [5, [1], {"compass": {"noise_std": rng.choice(odd_json)}},
                     {"battery": {"quantum": rng.choice(odd_json)}}, {"nope": {}}])}
            else:
                kw = {rng.choice(["n_clutter", "substeps", "control_period_s", "sensor_noise",
                                  "arena_size_m"]): rng.choice(odd_json)}
            try:
                text = json.dumps(kw)
            except ValueError:
                text = "{bad"
            return cat, (mkv, ["record", "--env", "MKVJam-v0", "--env-kwargs", text,
                               "--policy", "random", "--episodes", "1", "--out", p("o.npz")])
        if cat == "collision":
            return cat, rng.choice([
                (mkv, ["fit", p("data.npz"), "--out", p("data.npz")]),
                (mkv, ["train-bc", p("data.npz"), "--out", p("data.npz")]),
                (mkv, ["compare", p("data.npz"), p("policy.npz"), "--json", p("data.npz")]),
                (mkv, ["eval", "--env", "MKVJam-v0", "--policy", f"sfm:{p('policy.npz')}",
                       "--episodes", "1", "--json", p("policy.npz")]),
                (mkv, ["record", "--env", "MKVJam-v0", "--policy", "random", "--episodes", "1",
                       "--out", "/dev/null"]),
                (calib, ["fit", p("raw.csv"), "--dof", "3", "--out", p("raw.csv")]),
                (calib, ["apply", p("cal.json"), p("raw.csv"), "--out", p("cal.json")]),
                (calib, ["fit", p("loads.csv"), "--dof", "3", "--method", "least_squares",
                         "--out", p("loads.csv")]),
            ])
        if cat == "csv":
            z = paper_trial(2, rng=rng.randrange(100)).Z
            z[rng.randrange(len(z)), rng.randrange(8)] = rng.choice(
                [math.nan, math.inf, 1e308, -1e308])
            write_csv(p("bad.csv"), [f"g{i}" for i in range(8)], z)
            if rng.random() < 0.5:
                with open(p("bad.csv"), "wb") as f:
                    f.write(damaged("raw.csv"))
            return cat, rng.choice([
                (calib, ["fit", p("bad.csv"), "--dof", "3", "--bias", "--out", p("o.json")]),
                (calib, ["apply", p("cal.json"), p("bad.csv"), "--out", p("o.csv")]),
                (calib, ["evaluate", p("cal.json"), p("bad.csv"), "--known", p("loads.csv")]),
                (calib, ["evaluate", p("cal.json"), p("loads.csv"), "--known", p("bad.csv")]),
                (calib, ["plan", p("bad.csv")]),
                (calib, ["fit", p("bad.csv"), "--dof", "3", "--method", "least_squares",
                         "--out", p("o.json")]),
                (calib, ["fit", p("raw.csv"), "--dof", "3", "--bias", "--method", "joint",
                         "--known", p("bad.csv"), "--cv", "poses", "--out", p("o.json")]),
            ])
        doc = json.loads(originals["cal.json"])
        doc[rng.choice(["C", "offset", "dof", "channels", "diagnostics"])] = rng.choice(
            odd_json + [[[1, 2], [3]], "abc", [[math.nan] * 8] * 3])
        with open(p("bad.json"), "w") as f:
            f.write(json.dumps(doc))
        if rng.random() < 0.3:
            with open(p("bad.json"), "wb") as f:
                f.write(damaged("cal.json"))
        return cat, rng.choice([
            (calib, ["apply", p("bad.json"), p("raw.csv"), "--out", p("o.csv")]),
            (calib, ["evaluate", p("bad.json"), p("loads.csv")])])

    p_sout = os.path.join(d, "sout")
    counts, by_cat, problems = Counter(), Counter(), []
    for _ in range(args.cases):
        for n, b in originals.items():
            with open(os.path.join(d, n), "wb") as f:
                f.write(b)
        for n in ("o.npz", "o.zip", "o.json", "o.csv"):
            with contextlib.suppress(FileNotFoundError):
                os.unlink(os.path.join(d, n))
        with contextlib.suppress(FileNotFoundError):
            os.unlink(marker)
        shutil.rmtree(os.path.join(d, "sout"), ignore_errors=True)
        cat, (main, argv) = case()
        before = {n: hashlib.sha256(originals[n]).hexdigest() for n in originals}
        outcome, text = run(main, argv)
        if os.path.exists(marker):
            outcome = "code execution"
        after = {n: hashlib.sha256(open(os.path.join(d, n), "rb").read()).hexdigest()
                 for n in originals}
        if after != before:
            outcome = "input destroyed"
        if outcome == "refused" and any(os.path.exists(os.path.join(d, n))
                                        for n in ("o.npz", "o.zip", "o.json", "o.csv")):
            outcome = "partial output"
        if outcome == "accepted" and cat in ("file", "collision", "caljson", "fifo", "minari",
                                             "header") or (
                outcome == "accepted" and cat == "sweep" and os.path.isdir(p_sout)):
            outcome = "accepted (check)"
        counts[outcome] += 1
        by_cat[(cat, outcome)] += 1
        if outcome not in ("refused", "accepted"):
            problems.append((outcome, " ".join(str(a) for a in argv)[:160], text.strip()[:200]))
    for _ in range(args.interrupts):
        outcome, detail = interrupt_case(rng, d)
        counts[outcome] += 1
        by_cat[("interrupt", outcome)] += 1
        if outcome not in ("interrupted", "finished"):
            problems.append((outcome, str(detail)[:300], ""))
    print(f"{args.cases} cases, {args.interrupts} interrupts: "
          + ", ".join(f"{k} {v}" for k, v in counts.most_common()))
    for (cat, outcome), v in sorted(by_cat.items()):
        print(f"  {cat:<10} {outcome:<18} {v}")
    for p_ in problems[:30]:
        print("PROBLEM", *p_, sep="\n   ")
    return 1 if any(o in counts for o in ("traceback", "input destroyed", "partial output",
                                          "multi-line error", "hang", "code execution",
                                          "process left")) else 0


if __name__ == "__main__":
    sys.exit(main_())
