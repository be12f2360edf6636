"""``import torchconn`` sets ``OMP_WAIT_POLICY=PASSIVE`` only when it is what loads torch and the
variable is unset (torchconn/__init__.py; benchmarks/under_load.py measures why).

libgomp reads the variable once, when torch loads it, so what matters is its value at that
moment: a probe process stops ``import torchconn`` where it imports torch (an import hook that
records the variable there and refuses the import, so torch never loads and the import can be
repeated with another environment, ~1 s); torch imported first is a fresh process of its own."""
from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

PRINT = "import os; print(os.environ.get('OMP_WAIT_POLICY', '<unset>'))"

_PROBE = r"""
import json, os, sys

class AtTorch:
    # Record OMP_WAIT_POLICY at the moment torch would be imported, and refuse the import.
    seen = []
    def find_spec(self, name, path=None, target=None):
        if name == "torch":
            AtTorch.seen.append(os.environ.get("OMP_WAIT_POLICY", "<unset>"))
            raise ImportError("stopped by the test where torch would load")

sys.meta_path.insert(0, AtTorch())
out = {}
for case, value in (("torchconn-first", None), ("user-set", "ACTIVE")):
    os.environ.pop("OMP_WAIT_POLICY", None)
    if value is not None:
        os.environ["OMP_WAIT_POLICY"] = value
    for name in [m for m in sys.modules if m == "torchconn" or m.startswith("torchconn.")]:
        del sys.modules[name]
    n = len(AtTorch.seen)
    try:
        import torchconn
    except ImportError:
        pass
    out[case] = AtTorch.seen[n] if len(AtTorch.seen) > n else "torch was not imported"
    out[case + ":torch_loaded"] = "torch" in sys.modules
print(json.dumps(out))
"""


def _run(code: str, **env: str) -> str:
    base = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    out = subprocess.run([sys.executable, "-c", code], env={**base, **env}, capture_output=True, text=True,
                         timeout=120, check=True)
    return out.stdout.strip()


@pytest.fixture(scope="module")
def probe() -> dict:
    return json.loads(_run(_PROBE).splitlines()[-1])


@pytest.mark.parametrize(
    ("case", "expect"),
    [("torchconn-first", "PASSIVE"),  # torchconn loads torch: passive waiting
     ("user-set", "ACTIVE")],  # the user's choice wins
)
def test_wait_policy_when_torchconn_loads_torch(probe, case, expect):
    assert probe[case] == expect and probe[f"{case}:torch_loaded"] is False, probe


def test_wait_policy_is_left_alone_when_torch_loads_first():
    assert _run("import torch, torchconn; " + PRINT) == "<unset>"
