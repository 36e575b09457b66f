"""Another route's fit checked against the pose-level joint fit on the same static-pose log
(:func:`crosscheck`); the verdict reads the result (``diagnostics["crosscheck"]``,
:data:`calib.verdict.reliability.CROSSCHECK_FACTOR`)."""

from __future__ import annotations

import numpy as np


def crosscheck(cal, Z, known_Z, known_M) -> dict | None:
    """Compare ``cal`` (a route other than the pose fit) with the pose-level joint fit on the
    same static-pose log ``Z`` and known loads; None when ``Z`` has no static poses or the pose
    fit fails. Returns ``poses``, ``disagreement_rms`` (load units, over the pose means),
    ``reference_residual`` and their ``ratio``; stored as ``diagnostics["crosscheck"]``."""
    import warnings

    from calib.data.result import CalibrationError
    from calib.estimators.rig.poses import find_poses
    from calib.routes.joint import fit_joint

    Z = np.asarray(Z, float)
    labels = find_poses(Z)
    if labels is None:
        return None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            ref = fit_joint(Z, known_Z, known_M, cal.C.shape[0], poses=labels)
        except CalibrationError:
            return None
    j = ref.diagnostics.get("joint", {})
    if j.get("route") != "poses":
        return None
    ids = np.unique(labels[labels >= 0])
    means = np.array([Z[labels == i].mean(axis=0) for i in ids])
    D = float(np.sqrt(np.mean((cal.apply(means) - ref.apply(means)) ** 2)))
    scale = max(float(j["known_residual_rms"]), float(j["pose_magnitude_residual_rms"]),
                1e-12 * float(j["magnitude"]))
    return {"reference": "joint (poses)", "poses": len(ids), "disagreement_rms": D,
            "reference_residual": scale, "ratio": D / scale}
