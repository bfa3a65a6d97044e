"""A node started the way the Makefile starts nodes stays on loopback DDS."""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _make_env() -> dict[str, str]:
    # Start from an environment without the DDS variables, so the values seen
    # by the node can only have come from the Makefile.
    env = {k: v for k, v in os.environ.items() if not k.startswith(("ROS_", "RMW_", "MAKE"))}
    env.pop("MFLAGS", None)
    return env


def test_make_doctor_node_gets_localhost_discovery_and_its_own_domain():
    out = subprocess.run(
        ["make", "-s", "--no-print-directory", "doctor"],
        cwd=ROOT,
        env=_make_env(),
        capture_output=True,
        text=True,
        timeout=120,
        check=True,
    ).stdout
    report = json.loads(out[out.index("{") :])
    assert report["discovery_range"] == "LOCALHOST"
    assert report["loopback_only"] is True
    assert report["domain_id"] == 44
    assert report["rmw_implementation"] == "rmw_fastrtps_cpp"


def test_every_make_target_that_runs_nodes_sets_its_own_domain():
    makefile = (ROOT / "Makefile").read_text()
    assert "export ROS_AUTOMATIC_DISCOVERY_RANGE := LOCALHOST" in makefile
    domains = {}
    for target in ("demo", "test", "bench", "doctor"):
        prefix = f"{target}: export ROS_DOMAIN_ID"
        line = next(x for x in makefile.splitlines() if x.startswith(prefix))
        var = line.split("$(")[1].rstrip(")")
        value = next(x for x in makefile.splitlines() if x.startswith(f"{var} ?="))
        domains[target] = int(value.split("?=")[1])
    assert len(set(domains.values())) == len(domains), domains


def test_this_test_run_is_itself_on_loopback():
    # `make test` exports these; a bare `pytest` gets them from tests/conftest.py.
    assert os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST"
    assert os.environ["ROS_DOMAIN_ID"].isdigit()
