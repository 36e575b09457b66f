"""sfm_learn: the eigenspace (shape-from-motion) policy, its baselines, evaluation and reports.

Layers, each importing only the ones before it (``tests/test_layering.py`` checks this)::

    eigenspace/   projector, features, policy        the paper's learner
    evaluation/   records, bootstrap, runner,        episodes -> metrics with intervals;
                  compare, study                     Figure 3 agreement; the feature study
    baselines/    sb3, bc, dagger, ppo, sb3_models Stable-Baselines3 learners and policy files
    reporting/    tables, plots, report              Markdown, PNG, the demo report
    cli/          one module per ``mkv`` command     the only place argparse and CliError live

Library functions raise ``ValueError``/``TypeError`` (one-line messages); the ``mkv`` command
turns them into exit status 2.

Importing the package registers the policy specs of :data:`POLICY_LOADERS` with
:mod:`mkv_env.policies` (lazily: each loader module is imported only when its spec is used), so
any process that imports ``sfm_learn`` (an evaluation worker too) understands them.
"""

from mkv_env.policies import register_policy_loader as _register

__version__ = "0.1.0"

#: Policy-spec prefixes provided by sfm_learn: prefix -> "module:function" (imported on first use).
POLICY_LOADERS: dict[str, str] = {
    "sfm": "sfm_learn.eigenspace.policy:load_spec",
    "ppo": "sfm_learn.baselines.ppo:load_spec",
    "bc": "sfm_learn.baselines.bc:load_spec",
    "dagger": "sfm_learn.baselines.dagger:load_spec",
    "sb3": "sfm_learn.baselines.sb3_models:load_spec",
}

for _prefix, _target in POLICY_LOADERS.items():
    _register(_prefix, _target, replace=True)
