# The two set-up commands users rely on: `make demo` and `make test`.
# Each creates .venv if it is missing and installs the package with all extras.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test install lint bench clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip

# torch==2.13.0 first: an unpinned torch (pulled by stable-baselines3) would fetch GB of CUDA wheels.
$(STAMP): $(BIN)/python pyproject.toml
	$(BIN)/python -m pip install --quiet torch==2.13.0
	$(BIN)/python -m pip install --quiet -e ".[all]"
	touch $(STAMP)

install: $(STAMP)

# The end-to-end job as far as it exists: teacher data, evaluation on seeded jams, calib trials.
# (`mkv demo`, with SfM/BC/PPO and the report, replaces this once issue 6 lands.)
demo: $(STAMP)
	mkdir -p demo_out
	SDL_VIDEODRIVER=dummy MPLBACKEND=Agg $(BIN)/mkv record --env MKV-v0 --policy teacher --episodes 20 --seed 0 --out demo_out/teacher.npz
	SDL_VIDEODRIVER=dummy MPLBACKEND=Agg $(BIN)/mkv eval --env MKVJam-v0 --policy teacher --episodes 50 --seed 1000 --json demo_out/eval_teacher.json
	SDL_VIDEODRIVER=dummy MPLBACKEND=Agg $(BIN)/mkv eval --env MKVJam-v0 --policy random --episodes 50 --seed 1000 --json demo_out/eval_random.json
	SDL_VIDEODRIVER=dummy MPLBACKEND=Agg $(BIN)/calib trials --out demo_out/calib

test: $(STAMP)
	SDL_VIDEODRIVER=dummy MPLBACKEND=Agg $(BIN)/python -m pytest -q tests

lint: $(STAMP)
	$(BIN)/ruff check mkv_env sfm_learn calib tests benchmarks

bench: $(STAMP)
	$(BIN)/python benchmarks/env_speed.py

clean:
	rm -rf $(VENV) build *.egg-info demo_out
