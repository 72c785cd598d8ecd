"""The numerical configuration (adv3d_runner/machine.py, docs/reliability.md): what is read,
what is pinned, how another CPU is emulated, and what a resume on another configuration says."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from adv3d_runner import machine
from adv3d_runner.errors import ConfigError
from adv3d_runner.machine_cli import emulation_env

ROOT = Path(__file__).resolve().parent.parent
AVX512 = frozenset({"sse4_2", "avx", "avx2", "fma", "avx512f", "avx512cd", "avx512dq", "avx512bw", "avx512vl"})


def test_cpu_tier_is_the_highest_whose_flags_are_all_there():
    assert machine.cpu_tier(AVX512) == "avx512"
    assert machine.cpu_tier(AVX512 - {"avx512vl"}) == "avx2"  # Knights Landing: AVX-512 without VL
    assert machine.cpu_tier(frozenset({"sse4_2", "avx", "avx2"})) == "sse4.2"  # AVX2 without FMA
    assert machine.cpu_tier(frozenset({"sse4_2", "avx"})) == "sse4.2"
    assert machine.cpu_tier(frozenset({"sse2"})) is None
    assert machine.embree_native_isa(frozenset({"sse4_2", "avx"})) == "avx"  # Embree's own choice


def test_embree_isa_auto_pins_the_tier_and_refuses_what_the_cpu_cannot_run(monkeypatch):
    monkeypatch.setattr(machine, "cpu_flags", lambda: frozenset({"sse4_2", "avx", "avx2", "fma"}))
    monkeypatch.delenv("ADV3D_EMBREE_ISA", raising=False)
    assert machine.embree_isa() == "avx2"
    monkeypatch.setenv("ADV3D_EMBREE_ISA", "sse4.2")
    assert machine.embree_isa() == "sse4.2"
    monkeypatch.setenv("ADV3D_EMBREE_ISA", "avx512")
    with pytest.raises(ConfigError, match=r"ADV3D_EMBREE_ISA=avx512: this CPU lacks avx512bw.*runs at most avx2"):
        machine.embree_isa()
    monkeypatch.setenv("ADV3D_EMBREE_ISA", "avx9")
    with pytest.raises(ConfigError, match="ADV3D_EMBREE_ISA='avx9': expected auto or one of sse4.2, avx2, avx512"):
        machine.embree_isa()


def test_the_key_follows_the_kernels_not_the_cpu_name(monkeypatch):
    monkeypatch.delenv("ADV3D_EMBREE_ISA", raising=False)
    base = machine.numerical_config()
    monkeypatch.setattr(machine, "cpu_model", lambda: "Some Other CPU")
    assert machine.numerical_config()["key"] == base["key"]
    monkeypatch.setenv("ADV3D_EMBREE_ISA", "sse4.2")
    other = machine.numerical_config()
    assert other["embree_isa"] == "sse4.2" and "ADV3D_EMBREE_ISA=sse4.2" in other["env"]
    if base["embree_isa"] != "sse4.2":
        assert other["key"] != base["key"]
    assert "[key " in machine.describe_numerics(other)


def test_emulation_refuses_a_tier_above_the_cpus(monkeypatch):
    monkeypatch.setattr(machine, "cpu_flags", lambda: frozenset({"sse4_2", "avx"}))
    monkeypatch.setattr("adv3d_runner.machine_cli.cpu_tier", lambda: machine.cpu_tier(frozenset({"sse4_2"})))
    with pytest.raises(ConfigError, match="this CPU runs at most sse4.2"):
        emulation_env("avx2", {})
    with pytest.raises(ConfigError, match="expected one of"):
        emulation_env("neon", {})
    assert emulation_env("sse4.2", {"A": "1"})["ADV3D_EMBREE_ISA"] == "sse4.2"


_CHILD = """
import json, torch, numpy as np
from adv3d_runner.machine import numerical_config
from adv3d_runner.sensors import embree
from adv3d_runner.sensors.world import LidarWorld
w = LidarWorld(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], float), np.array([[0, 1, 2]]))
print(json.dumps({**numerical_config(), "device_isa": embree.isa(), "coherent": w.background.certificates is not None}))
"""


@pytest.mark.skipif(machine.cpu_tier() is None, reason="needs an x86-64 CPU with SSE4.2")
def test_an_emulated_sse42_cpu_runs_every_library_at_its_lowest_kernels():
    """The emulation's variables reach each library: numpy's dispatch, OpenBLAS's kernel,
    torch's capability (read from torch itself), Embree's device and the coherent-cast choice."""
    env = {**emulation_env("sse4.2"), "PYTHONPATH": str(ROOT)}
    out = subprocess.run([sys.executable, "-c", _CHILD], env=env, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    cfg = json.loads(out.stdout.strip().splitlines()[-1])
    assert cfg["numpy_simd"] == "SSE42" and cfg["blas"] == "openblas Nehalem"
    assert cfg["torch_capability"] == "DEFAULT" and cfg["numba_target"] == "nehalem"
    assert cfg["device_isa"] == cfg["embree_isa"] == "sse4.2" and cfg["coherent"] is False
    here = machine.numerical_config()
    if here["embree_isa"] != "sse4.2":  # (this suite may itself run under the emulation)
        assert cfg["key"] != here["key"]


def test_numerics_command_prints_the_configuration():
    out = subprocess.run([sys.executable, "-m", "adv3d_runner.cli", "numerics", "--json"], capture_output=True,
                         text=True, timeout=120, env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert out.returncode == 0, out.stderr
    cfg = json.loads(out.stdout)
    assert cfg["key"] == machine.numerical_config()["key"]
    bad = subprocess.run([sys.executable, "-m", "adv3d_runner.cli", "numerics", "echo"], capture_output=True,
                         text=True, timeout=120, env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert bad.returncode == 1 and "needs --emulate" in bad.stderr


def test_a_resume_on_another_configuration_says_so(tmp_path, capsys, monkeypatch):
    from adv3d_runner.attack.journal import Journal

    monkeypatch.setattr("adv3d_runner.progress._QUIET", False)  # an earlier test may have set -q

    doc = {"algo": "random", "budget": 3, "versions": {"adv3d": "1", "numerics": machine.numerical_config()}}
    Journal(tmp_path / "run").start(doc)
    capsys.readouterr()
    Journal(tmp_path / "run").start(doc)
    assert "numerical configuration" not in capsys.readouterr().out
    other = {**doc["versions"]["numerics"], "embree_isa": "elsewhere", "key": "0123456789ab"}
    Journal(tmp_path / "run").start({**doc, "versions": {"adv3d": "1", "numerics": other}})
    said = capsys.readouterr().out
    assert "another numerical configuration" in said and "numerics.embree_isa:" in said
    assert "other versions" not in said  # only the configuration changed
