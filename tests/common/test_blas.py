"""numpy's and scipy's BLAS run on one thread in the commands that compute; a user's choice wins."""
from __future__ import annotations

import json
import os
import subprocess
import sys

from dibrgs_core.common import blas

# What a computing command does at start (options.apply_compute), then the BLAS pools as
# threadpoolctl sees them, and the log's wording.
PROBE = r"""
import argparse, json, os, sys
if os.environ.get("HIDE_THREADPOOLCTL"):
    sys.modules["threadpoolctl"] = None  # importing it now fails, as where it is not installed
from dibrgs_core.commands.options import apply_compute
from dibrgs_core.common.blas import blas_policy
apply_compute(argparse.Namespace(threads=2, rasterizer=None))
pools = []
if not os.environ.get("HIDE_THREADPOOLCTL"):
    from threadpoolctl import threadpool_info
    pools = [(i["filepath"], i["num_threads"]) for i in threadpool_info() if i["user_api"] == "blas"]
print(json.dumps({"pools": pools, "policy": blas_policy()}))
"""


def probe(**env: str) -> dict:
    clean = {k: v for k, v in os.environ.items() if k not in blas.USER_VARIABLES}
    out = subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True, check=True,
                         env={**clean, **env})
    return json.loads(out.stdout.splitlines()[-1])


def test_numpy_and_scipy_blas_get_one_thread():
    got = probe()
    assert got["pools"], got  # numpy's and scipy's own OpenBLAS in the wheels; one shared library elsewhere
    assert all(n == 1 for _, n in got["pools"]), got
    assert got["policy"].startswith("one thread")


def test_the_users_own_blas_threads_are_left_alone():
    got = probe(OPENBLAS_NUM_THREADS="2")
    assert got["policy"] == "the user's OPENBLAS_NUM_THREADS"
    if os.cpu_count() and os.cpu_count() >= 2:
        assert any(n == 2 for _, n in got["pools"]), got


def test_without_threadpoolctl_the_command_still_runs_and_says_so():
    got = probe(HIDE_THREADPOOLCTL="1")
    assert got["policy"].startswith("the BLAS libraries' defaults (threadpoolctl is not installed")
