"""pidg's process-wide OpenMP defaults: set before torch loads, and a user's own values win."""
import os
import subprocess
import sys

import pytest

from pidg._env import GOMP_SPIN_ITERATIONS

SHOW = "import os, pidg, torch; print(os.environ['OMP_WAIT_POLICY'], os.environ['GOMP_SPINCOUNT'])"


def _run(env_overrides: dict[str, str]) -> list[str]:
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")}
    env.update(env_overrides)
    return subprocess.run([sys.executable, "-c", SHOW], env=env, check=True, capture_output=True, text=True).stdout.split()


def test_importing_pidg_sets_a_passive_policy_with_a_bounded_spin():
    assert _run({}) == ["PASSIVE", str(GOMP_SPIN_ITERATIONS)]


@pytest.mark.parametrize("policy, spin", [("ACTIVE", "0"), ("PASSIVE", "0")])
def test_the_user_s_own_openmp_settings_win(policy, spin):
    assert _run({"OMP_WAIT_POLICY": policy, "GOMP_SPINCOUNT": spin}) == [policy, spin]
