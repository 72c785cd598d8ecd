"""bench/sanity.py's planner options fail early, with the field named, and write nothing."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parent.parent


def _sanity(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(ROOT / "bench" / "sanity.py"), "--sets", "real", *args],
                          capture_output=True, text=True, timeout=120, cwd=ROOT)


@pytest.mark.parametrize("args, message", [
    (["--planner-config", '{"proposals": {"max_jerk": 1}}'], "needs --name or --tag"),
    (["--planner-config", '{"proposals": {"max_jerks": 1}}', "--tag", "t"], "proposals.max_jerks is not a field"),
    (["--planner-config", "{bad", "--tag", "t"], "not JSON"),
    (["--planner-config", "missing-dir/tune.json", "--tag", "t"], "cannot read missing-dir/tune.json"),
    (["--planner-config", "{}", "--planner-limits", "before-issue17", "--tag", "t"], "exclusive"),
    (["--name", "/tmp/out"], "--name is a file stem"),
    (["--sets", "generated", "--generated-dir", "scenes/highway"], "--generated-dir needs --name"),
    (["--sets", "generated", "--generated-dir", "no-such-dir", "--name", "x"], "no scene files"),
    (["--seed", "3"], "--seed other than 0 needs --name or --tag"),
    (["--real-dir", "scenes/real-train-egos"], "--real-dir needs --name"),
    # tuning on extra scenes cannot reach the benchmark recordings
    (["--real-dir", "scenes/real", "--name", "x"], "recording 4 is not in the train part"),
    (["--real-dir", "scenes/highway", "--name", "x"], "does not name a CommonRoad US-101 recording"),
])
def test_bad_planner_options_stop_before_any_episode(args, message):
    before = sorted((ROOT / "bench" / "results").iterdir())
    done = _sanity(*args)
    assert done.returncode == 2, done.stderr
    assert message in done.stderr
    assert sorted((ROOT / "bench" / "results").iterdir()) == before


def test_planner_config_file_is_read(tmp_path):
    bad = tmp_path / "tune.json"
    bad.write_text(json.dumps({"weights": {"no_such_term": 1.0}}))
    done = _sanity("--planner-config", str(bad), "--tag", "t")
    assert done.returncode == 2 and f"{bad}: weights.no_such_term is not a field" in done.stderr


def test_real_seed_files_behind_the_jerk_figure_hold_twenty_seeds_of_the_same_scenes():
    """``bench/real_seeds_plot.py`` reads the kept real-benchmark files of two planners; each set
    holds 20 seeds of the same 7 scenes, and the seeds differ (the sensor's noise is seeded)."""
    sys.path.insert(0, str(ROOT / "bench"))
    try:
        import real_seeds_plot
    finally:
        sys.path.remove(str(ROOT / "bench"))
    for files in real_seeds_plot.PLANNERS.values():
        names, jerk = real_seeds_plot.drive_jerks(files)
        assert jerk.shape == (20, 7) and len(names) == 7 and np.isfinite(jerk).all()
        assert len({tuple(row) for row in jerk.round(6)}) > 10
