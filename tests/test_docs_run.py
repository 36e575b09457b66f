"""Docs that run: every shell and Python block of README.md and docs/*.md, in a scratch folder.

Conventions the docs follow (and this test enforces):

- Every fenced block is labelled: ``sh`` / ``bash`` (run with bash, ``-e``: a failing line fails
  the test), ``python`` (run with this interpreter), or ``text`` (synopses, trees, file formats;
  not run).
- The blocks of one page run in order in one scratch folder, so a later block may use the files an
  earlier one wrote; a Python block may use the names an earlier Python block of the page imported
  (its import lines are carried forward, nothing else).
- An HTML comment on the line before a block changes how it runs:
  ``<!-- docs-test: quick -->``  run with the rewrites in ``QUICK`` (fewer episodes, steps, seeds);
  every rewrite is listed below with the reason, and a block marked quick must match at least one.
  ``<!-- docs-test: skip REASON -->``  not run; REASON says where the same thing is tested.
- Files a page takes for granted (a zarr array, a dataset to export) are made by ``SETUP``,
  keyed by the page and the start of the block's first line. ``sweeps/``, ``scripts/`` and
  ``examples/`` (the bundled calibration logs of ``examples/calib/``) are copied into the
  scratch folder first.
"""

from __future__ import annotations

import os
import pathlib
import re
import shutil
import subprocess
import sys

import pytest
import yaml

ROOT = pathlib.Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
BIN = pathlib.Path(sys.executable).parent
FENCE = re.compile(r"^```(\S*)\s*$")
MARK = re.compile(r"^<!--\s*docs-test:\s*(quick|skip)\b\s*(.*?)\s*-->\s*$")
RUNNABLE = {"sh", "bash", "python"}
LABELS = RUNNABLE | {"text"}

# (pattern, replacement, why): applied to blocks marked quick, in this order.
QUICK = [
    (r"--episodes (\d{2,})", "--episodes 2", "episodes: 2, not tens to 10,000"),
    (r"--steps \d+ --rounds \d+", "--steps 600 --rounds 2 --min-updates 50",
     "DAgger: 600 steps in 2 rounds, 50 minibatch updates per refit instead of 1,000"),
    (r"(mkv train-bc[^\n#]*?--out \S+)", r"\1 --min-updates 50",
     "BC: 50 minibatch updates instead of 1,000 (the zip it writes is the same kind)"),
    (r"(mkv train-ppo[^\n#]*?--out \S+)", r"\1 --timesteps 256 --n-envs 2 --eval-episodes 1",
     "PPO: one short rollout instead of 500k steps"),
    (r"\.learn\(100_000\)", ".learn(256)", "SB3 PPO: one rollout"),
    (r"SB3VecEnv\(\"MKV-v1\", n_envs=16, seed=0\)\)",
     "SB3VecEnv(\"MKV-v1\", n_envs=2, seed=0), n_steps=128, batch_size=64)",
     "SB3 PPO: 2 envs x 128 steps per rollout instead of 16 x 2048"),
    (r"\n\s*mkv teleop[^\n]*", "",
     "teleop needs a keyboard and a window: tests/mkv_env/test_teleop.py"),
    (r"--workers 2\b", "--workers 1", "one worker (the suite already uses the cores)"),
    (r"calib trials --out (\S+)", r"calib trials --out \1 --seeds 3 --quiet", "3 seeds, not 200"),
    (r"python scripts/sfm_study.py", "python scripts/sfm_study.py --quick --workers 1 --sets 1",
     "one training set, few episodes"),
]


def _quick_sweep(scratch: pathlib.Path) -> None:
    """sweeps/sample_efficiency.yml cut to one seed, two learners, one budget, 2 episodes, BC
    fitted with 50 minibatch updates instead of 1,000."""
    spec = yaml.safe_load((ROOT / "sweeps" / "sample_efficiency.yml").read_text())
    spec.update(env=["MKVJam-v1"], seeds=[0], eval={"episodes": 2, "seed": spec["eval"]["seed"]})
    spec["learners"] = {k: spec["learners"][k] for k in ("sfm", "bc")}
    spec["learners"]["bc"] = {**spec["learners"]["bc"], "min_updates": 50}
    spec["budgets"] = {"sfm": [600], "bc": [600]}
    (scratch / "sweeps").mkdir(exist_ok=True)
    (scratch / "sweeps" / "sample_efficiency.yml").write_text(yaml.safe_dump(spec))


def _zarr_log(scratch: pathlib.Path) -> None:
    import zarr

    from calib.simulation.simulate import paper_trial

    Z = paper_trial(2, rng=0).Z
    arr = zarr.open(str(scratch / "log.zarr"), mode="w", shape=Z.shape, chunks=(500, Z.shape[1]),
                    dtype="f8")
    arr[:] = Z


def _teacher_npz(scratch: pathlib.Path) -> None:
    _sh(scratch, "mkv record --env MKVJam-v0 --policy teacher --episodes 2 --seed 0 "
                 "--out teacher.npz --quiet")


SETUP = {
    ("calib.md", "import dask.array"): _zarr_log,
    ("minari.md", "mkv export teacher.npz"): _teacher_npz,
}


def _blocks(page: pathlib.Path):
    """(first line number, label, mark, mark text, code) of every fenced block."""
    lines = page.read_text().splitlines()
    out, i = [], 0
    while i < len(lines):
        m = FENCE.match(lines[i])
        if not m:
            i += 1
            continue
        start, label = i, m.group(1)
        prev = lines[i - 1] if i else ""
        mk = MARK.match(prev)
        j = i + 1
        while j < len(lines) and not FENCE.match(lines[j]):
            j += 1
        assert j < len(lines), f"{page.name}:{start + 1}: unclosed code block"
        out.append((start + 1, label, mk.group(1) if mk else None, mk.group(2) if mk else "",
                    "\n".join(lines[i + 1:j])))
        i = j + 1
    return out


def _env(scratch: pathlib.Path) -> dict:
    env = dict(os.environ)
    env.update(PATH=f"{BIN}{os.pathsep}{env.get('PATH', '')}", SDL_VIDEODRIVER="dummy",
               MPLBACKEND="Agg", MINARI_DATASETS_PATH=str(scratch / "minari"),
               PYTHONPATH=str(ROOT), TQDM_DISABLE="1", OMP_NUM_THREADS="1")
    return env


def _sh(scratch: pathlib.Path, code: str, label: str = "sh") -> None:
    if label == "python":
        argv = [sys.executable, "-c", code]
    else:
        argv = ["bash", "-euo", "pipefail", "-c", code]
    r = subprocess.run(argv, cwd=scratch, env=_env(scratch), capture_output=True, text=True,
                       timeout=600)
    assert r.returncode == 0, (
        f"exit {r.returncode}\n--- code\n{code}\n--- stdout (tail)\n{r.stdout[-2000:]}"
        f"\n--- stderr (tail)\n{r.stderr[-3000:]}")


def _quick(code: str) -> tuple[str, int]:
    hits = 0
    for pat, rep, _why in QUICK:
        code, n = re.subn(pat, rep, "\n" + code)
        code = code[1:]
        hits += n
    return code, hits


def _imports(code: str) -> list[str]:
    return [ln for ln in code.splitlines() if re.match(r"^(import|from)\s+\S+", ln)]


def _pages_with_code():
    return [p for p in PAGES if _blocks(p)]


@pytest.mark.parametrize("page", _pages_with_code(), ids=lambda p: p.name)
def test_every_block_is_labelled_and_every_mark_is_used(page):
    for line, label, mark, why, code in _blocks(page):
        where = f"{page.name}:{line}"
        assert label in LABELS, f"{where}: label the block ({sorted(LABELS)}), not {label!r}"
        if mark == "skip":
            assert len(why) > 10, f"{where}: a skipped block says why and where it is tested"
        if mark == "quick":
            assert _quick(code)[1] > 0, f"{where}: marked quick but no QUICK rewrite applies"
        if mark and label == "text":
            raise AssertionError(f"{where}: a text block is never run; drop the mark")
    for (name, start), _fn in SETUP.items():
        if name == page.name:
            assert any(c.lstrip().startswith(start) for *_, c in _blocks(page)), (
                f"SETUP key {start!r} matches no block of {name}")


@pytest.mark.parametrize("page", _pages_with_code(), ids=lambda p: p.name)
def test_every_block_runs(page, tmp_path):
    blocks = [b for b in _blocks(page) if b[1] in RUNNABLE and b[2] != "skip"]
    if not blocks:
        pytest.skip(f"{page.name}: no block to run")
    for d in ("sweeps", "scripts", "examples"):
        shutil.copytree(ROOT / d, tmp_path / d)
    if page.name == "README.md":
        _quick_sweep(tmp_path)
    imports: list[str] = []
    for line, label, mark, _why, code in blocks:
        for (name, start), fn in SETUP.items():
            if name == page.name and code.lstrip().startswith(start):
                fn(tmp_path)
        run = _quick(code)[0] if mark == "quick" else code
        if label == "python":
            run = "\n".join(imports + [run])
            imports += _imports(code)
        try:
            _sh(tmp_path, run, label)
        except AssertionError as e:
            raise AssertionError(f"{page.name}:{line}: {e}") from None
