"""sfm_learn: the eigenspace (shape-from-motion) projector policy, baselines and evaluation.

Importing the package registers the policy specs ``sfm:PATH``, ``ppo:PATH`` and ``bc:PATH`` with
:mod:`mkv_env.policies` (lazily: each loader module is imported only when its spec is used), so
any process that imports ``sfm_learn`` (a worker of ``mkv eval --workers`` too) understands them.
"""

from mkv_env.policies import register_policy_loader as _register

__version__ = "0.1.0"

#: Policy-spec prefixes provided by sfm_learn: prefix -> "module:function" (imported on first use).
POLICY_LOADERS: dict[str, str] = {
    "sfm": "sfm_learn.policy:load_spec",
    "ppo": "sfm_learn.ppo:load_spec",
    "bc": "sfm_learn.bc:load_spec",
}

for _prefix, _target in POLICY_LOADERS.items():
    _register(_prefix, _target, replace=True)
