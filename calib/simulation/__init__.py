"""Simulated sensors and rigs, the paper's section 8 trials, rig planning and the trials' plots.
"""
