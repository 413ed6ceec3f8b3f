"""OpenMP's wait policy follows how busy the CPU is when a stage starts (data.cpu_load)."""

from __future__ import annotations

import subprocess
import sys

import pytest

from nerfpipe.data import cpu_load


def test_a_busy_core_is_seen():
    """A child process spinning on one core shows as about one busy core (other processes can only add to it)."""
    if cpu_load.busy_cores(0.05) is None:
        pytest.skip("no /proc/stat on this system")
    spin = subprocess.Popen([sys.executable, "-c", "import time\nt = time.time()\nwhile time.time() - t < 5: pass"])
    try:
        busy = cpu_load.busy_cores(0.5)
    finally:
        spin.kill()
        spin.wait()
    assert busy is not None and busy >= 0.7, busy


@pytest.mark.parametrize(("busy", "expected"), [(1.0, "PASSIVE"), (0.1, None), (None, None)])
def test_passive_waits_only_when_other_work_keeps_a_core_busy(monkeypatch, busy, expected):
    monkeypatch.setattr(cpu_load, "busy_cores", lambda: busy)
    env: dict[str, str] = {}
    assert cpu_load.wait_policy(env, torch_loaded=False) == expected
    assert env.get("OMP_WAIT_POLICY") == expected


def test_the_users_setting_and_a_loaded_torch_are_left_alone(monkeypatch):
    def never() -> float:
        raise AssertionError("sampled the CPU although nothing could change")

    monkeypatch.setattr(cpu_load, "busy_cores", never)
    env = {"OMP_WAIT_POLICY": "ACTIVE"}
    assert cpu_load.wait_policy(env, torch_loaded=False) is None and env == {"OMP_WAIT_POLICY": "ACTIVE"}
    env = {}
    assert cpu_load.wait_policy(env, torch_loaded=True) is None and env == {}
