"""Shared fixtures of the test suite, and its seeding.

Every test starts from the same random state: an autouse fixture seeds
``random``, ``numpy.random`` and ``torch`` from ``ROBOTMEM_TEST_SEED``
(default ``0``) before each test (HER's "future" offsets, samplers without a
generator and collectors draw from the global generators), and a failing test's report carries a
"seed" section naming the value to replay it with. Tests that draw a
schedule of their own (the SIGKILL loops) take their seed from
:func:`seed_from_env`: their own variable if set, else ``ROBOTMEM_TEST_SEED``.
"""
from __future__ import annotations

import os
import random
import tempfile

import numpy as np
import pytest
import torch
from tensordict import TensorDict

from torchrl_robotmem.storage.rowfile import CACHE_ENV

torch.set_num_threads(1)

TEST_SEED_ENV = "ROBOTMEM_TEST_SEED"
DEFAULT_TEST_SEED = 0


def suite_seed() -> int:
    """The suite's seed: ``$ROBOTMEM_TEST_SEED``, else 0."""
    return int(os.environ.get(TEST_SEED_ENV, DEFAULT_TEST_SEED))


def seed_from_env(name: str) -> int:
    """A test's own seed: ``$<name>`` if set, else the suite's seed (:func:`suite_seed`)."""
    return int(os.environ.get(name, suite_seed()))


_SEED_KEY = pytest.StashKey[int]()


@pytest.fixture(autouse=True)
def _seed_every_test(request):
    seed = suite_seed()
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)
    request.node.stash[_SEED_KEY] = seed


FULL_ENV = "ROBOTMEM_FULL"


def pytest_configure(config):
    # row files of URL stores (and readers' private ones) under a folder of this run, never ~/.cache
    os.environ.setdefault(CACHE_ENV, tempfile.mkdtemp(prefix="robotmem-test-cache-"))
    config.addinivalue_line(
        "markers", f"full: a second test of a capability the default tier already covers, a minute or so; "
        f"runs with {FULL_ENV}=1 (make test-full), which every landing runs too")


def pytest_collection_modifyitems(config, items):
    if os.environ.get(FULL_ENV) == "1":
        return
    skip = pytest.mark.skip(reason=f"full tier: {FULL_ENV}=1 or make test-full (make test stays under 15 minutes)")
    for item in items:
        if item.get_closest_marker("full") is not None:
            item.add_marker(skip)


def pytest_report_header(config):
    tier = "full" if os.environ.get(FULL_ENV) == "1" else f"default (the full tier: {FULL_ENV}=1)"
    return (f"{TEST_SEED_ENV}={suite_seed()} (random, numpy and torch are seeded with it before every test); "
            f"tier: {tier}")


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    outcome = yield
    report = outcome.get_result()
    if report.failed:
        seed = item.stash.get(_SEED_KEY, suite_seed())
        report.sections.append(
            ("seed", f"{TEST_SEED_ENV}={seed} (random, numpy and torch were seeded with it before this test; "
                     f"set it to replay or vary the draw)")
        )


def make_transitions(n: int, start: int = 0, *, episode_len: int = 10, goal_dim: int = 3) -> TensorDict:
    """Deterministic FetchPush-shaped transitions; row i is a function of ``start + i``."""
    i = torch.arange(start, start + n)
    done = ((i + 1) % episode_len == 0).unsqueeze(-1)
    step = (i % episode_len).unsqueeze(-1)
    goal = torch.stack([torch.sin(i * 0.1), torch.cos(i * 0.1), i * 1e-3] + [i * 0.0] * (goal_dim - 3), -1).float()
    return TensorDict(
        {
            "observation": (i.unsqueeze(-1) + torch.arange(25)).float(),
            "achieved_goal": goal,
            "desired_goal": torch.zeros(n, goal_dim),
            "action": -i.float().unsqueeze(-1).expand(n, 4).clone(),
            "done": torch.zeros(n, 1, dtype=torch.bool),
            "step_count": step,
            "next": {
                "observation": (i.unsqueeze(-1) + torch.arange(25) + 1).float(),
                "achieved_goal": goal + 0.01,
                "desired_goal": torch.zeros(n, goal_dim),
                "reward": -torch.ones(n, 1),
                "done": done,
                "truncated": done.clone(),
                "terminated": torch.zeros(n, 1, dtype=torch.bool),
                "is_success": (i % 7 == 0).float(),
                "step_count": step + 1,
            },
        },
        [n],
    )


@pytest.fixture
def transitions():
    return make_transitions
