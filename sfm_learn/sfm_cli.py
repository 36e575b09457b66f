"""``mkv fit`` and ``mkv compare``: fit a shape-from-motion policy; the paper's Figure 3."""

from __future__ import annotations


def add_fit_arguments(p):
    p.add_argument("data", metavar="DATA.npz")
    p.add_argument("--out", required=True, metavar="POLICY.npz")


def run_fit(args):
    raise NotImplementedError


def add_compare_arguments(p):
    p.add_argument("data", metavar="DATA.npz")
    p.add_argument("policy", metavar="POLICY.npz")


def run_compare(args):
    raise NotImplementedError
