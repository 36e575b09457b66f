"""Placeholder: being written."""


def add_arguments(p):
    pass


def run(args):
    raise NotImplementedError


def load_spec(arg, env, seed):
    raise NotImplementedError
