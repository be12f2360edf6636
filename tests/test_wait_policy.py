"""``import torchconn`` sets ``OMP_WAIT_POLICY=PASSIVE`` only when it is what loads torch and the
variable is unset (torchconn/__init__.py; benchmarks/under_load.py measures why)."""
from __future__ import annotations

import os
import subprocess
import sys

import pytest

PRINT = "import os; print(os.environ.get('OMP_WAIT_POLICY', '<unset>'))"


def _run(code: str, **env: str) -> str:
    base = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    out = subprocess.run([sys.executable, "-c", code], env={**base, **env}, capture_output=True, text=True,
                         timeout=120, check=True)
    return out.stdout.strip()


@pytest.mark.parametrize(
    ("code", "env", "expect"),
    [
        ("import torchconn; " + PRINT, {}, "PASSIVE"),  # torchconn loads torch: passive waiting
        ("import torch, torchconn; " + PRINT, {}, "<unset>"),  # torch was loaded first: left alone
        ("import torchconn; " + PRINT, {"OMP_WAIT_POLICY": "ACTIVE"}, "ACTIVE"),  # the user's choice wins
    ],
    ids=["torchconn-first", "torch-first", "user-set"],
)
def test_wait_policy_is_a_default_set_before_torch_loads(code, env, expect):
    assert _run(code, **env) == expect
