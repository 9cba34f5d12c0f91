"""The OpenMP wait policy is chosen from the CPUs' use at start, before torch loads libgomp."""
from __future__ import annotations

import json
import os
import subprocess
import sys

from dibrgs_core.common import openmp


def test_idle_cpus_get_a_short_spin_busy_ones_passive_waiting_and_the_users_choice_wins():
    env: dict[str, str] = {}
    assert "short spin" in openmp.set_wait_policy(env, busy=0.1)
    assert env == {"GOMP_SPINCOUNT": openmp.SHORT_SPIN}
    env = {}
    assert "1.20 CPUs busy" in openmp.set_wait_policy(env, busy=1.2) and env == {"OMP_WAIT_POLICY": "PASSIVE"}
    assert openmp.wait_policy().startswith("passive")
    for mine in ({"OMP_WAIT_POLICY": "ACTIVE"}, {"GOMP_SPINCOUNT": "5"}):
        env = dict(mine)
        assert "the user's" in openmp.set_wait_policy(env, busy=0.0) and env == mine


def test_busy_cpus_reads_this_machine():
    busy = openmp.busy_cpus(0.05)
    if sys.platform.startswith("linux"):
        assert busy is not None and 0.0 <= busy <= os.cpu_count() + 1e-6
    else:
        assert busy is None


def test_the_command_sets_it_before_torch_loads():
    """`python -m dibrgs_core` decides before importing torch: the variable is in the environment
    libgomp reads, and the user's own setting is kept."""
    code = ("import json, os\n"
            "from dibrgs_core import cli\n"
            "assert cli.main(['info', '/no/such/scene']) != 0\n"
            "print(json.dumps({k: os.environ.get(k) for k in ('OMP_WAIT_POLICY', 'GOMP_SPINCOUNT')}))\n")
    base = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")}
    out = subprocess.run([sys.executable, "-c", code], env=base, capture_output=True, text=True, check=True)
    got = json.loads(out.stdout.strip().splitlines()[-1])
    assert (got["OMP_WAIT_POLICY"] == "PASSIVE") != (got["GOMP_SPINCOUNT"] == openmp.SHORT_SPIN)
    out = subprocess.run([sys.executable, "-c", code], env={**base, "OMP_WAIT_POLICY": "ACTIVE"},
                         capture_output=True, text=True, check=True)
    assert json.loads(out.stdout.strip().splitlines()[-1]) == {"OMP_WAIT_POLICY": "ACTIVE", "GOMP_SPINCOUNT": None}
