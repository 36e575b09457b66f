"""Shared helpers of the calib tests."""

import importlib.util
import warnings
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

SCRIPTS = Path(__file__).resolve().parents[2] / "scripts"


@pytest.fixture(scope="session")
def load_script():
    """``load_script("calib_real_rig")``: a script of scripts/ imported as a module."""

    def load(name: str):
        spec = importlib.util.spec_from_file_location(name, SCRIPTS / f"{name}.py")
        mod = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(mod)
        return mod

    return load


def _payload_joint(seed, **kw):
    """The payload study's protocol on ``simulate_payload_rig(seed, poses=80, **kw)``: every
    other pose trains, the others test; 4 known loads on the poses ``choose_known_poses``
    picks, one reading each; ``fit_joint`` with its warnings held back. Returns a namespace:
    ``rig, tr, te, M`` (every reading's stated load), ``kn`` (known rows of the training
    readings), ``cal``, ``err`` (held-out load rms) and ``rms`` (that function)."""
    from calib import fit_joint
    from calib.routes.joint import choose_known_poses
    from calib.simulation.simulate import simulate_payload_rig

    rig = simulate_payload_rig(seed, **({"poses": 80} | kw))
    tr, te = rig.split("poses")
    M = rig.stated_loads[rig.pose]
    Mt = M[tr]
    kn = choose_known_poses(Mt / np.linalg.norm(Mt, axis=1, keepdims=True), 4)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cal = fit_joint(rig.Z[tr], rig.Z[tr][kn], Mt[kn], 3, known_samples=1)

    def rms(cal_):
        return float(np.sqrt(np.mean(np.sum((cal_.apply(rig.Z[te]) - M[te]) ** 2, axis=1))))

    return SimpleNamespace(rig=rig, tr=tr, te=te, M=M, kn=kn, cal=cal, err=rms(cal), rms=rms)


@pytest.fixture(scope="session")
def payload_joint():
    """:func:`_payload_joint` (the same function every time: tests may cache on it)."""
    return _payload_joint
