"""The CLI's process environment: OpenMP threads wait passively unless the user says otherwise."""
from __future__ import annotations

import os
import subprocess
import sys

import pytest

PROBE = ("import os, sys; from hgca_core import cli; sys.argv = ['hgca', '--version']\n"
         "try:\n    cli.main()\nexcept SystemExit:\n    pass\nprint(os.environ.get('OMP_WAIT_POLICY'))")


@pytest.mark.parametrize("given, want", [(None, "PASSIVE"), ("ACTIVE", "ACTIVE")])
def test_omp_wait_policy_defaults_to_passive(given: str | None, want: str) -> None:
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    if given:
        env["OMP_WAIT_POLICY"] = given
    out = subprocess.run([sys.executable, "-c", PROBE], env=env, capture_output=True, text=True, timeout=60)
    assert out.stdout.strip().splitlines()[-1] == want, out.stderr
