"""Experiments over many training runs: sweeps (:mod:`.sweep`) and their curves
(:mod:`.summary`). Above baselines and reporting, below the command line."""
