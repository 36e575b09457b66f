"""sfm_learn: the eigenspace (shape-from-motion) projector policy, baselines and evaluation."""

__version__ = "0.1.0"
