import math
import os

import gymnasium as gym
import numpy as np
import pytest

import mkv_env  # noqa: F401
from mkv_env.envs import _place

os.environ.setdefault("SDL_VIDEODRIVER", "dummy")

FWD, OFF, REV = 2, 1, 0
LEFT, RIGHT = 0, 2


def open_floor(**kwargs):
    """An empty, noise-free 4 m arena with the robot at the centre facing +x."""
    kw = dict(n_clutter=0, n_patches=0, sensor_noise=0.0)
    kw.update(kwargs)
    env = gym.make("MKV-v0", **kw).unwrapped
    env.reset(seed=0)
    place(env, (2.0, 2.0, 0.0))
    return env


def place(env, pose):
    _place(env.world, pose)
    env.tracker.reset(pose)
    env.sensors.reset(env.np_random, env.world)


def run(env, action, steps):
    out = [env.step(np.array(action)) for _ in range(steps)]
    return out


def speed(env):
    vx, vy = env.world.robot.body.velocity
    return math.hypot(vx, vy)


def ch(env, obs, name):
    return float(obs[env.sensor_names.index(name)])


@pytest.fixture
def floor_env():
    env = open_floor()
    yield env
    env.close()
