"""The experiment protocol (attack/protocol.py): the scene-set rule, held-out evaluation seeds,
the held-out store and the per-scene aggregation."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from adv3d_runner.attack.config import scene_seed
from adv3d_runner.attack.protocol import (HeldoutStore, HeldoutTask, evaluation_seeds, metric_value, run_heldout,
                                          scene_means, select_scenes)
from adv3d_runner.errors import Adv3dError, ConfigError, FileFormatError
from adv3d_runner.scene.generate import DENSITIES


def test_scene_set_covers_every_density_then_the_real_recordings():
    five = select_scenes(5, 3)
    gen = [s for s in five if s.part == "generated"]
    real = [s for s in five if s.part == "real"]
    assert [s.density for s in gen] == list(DENSITIES)           # one per density, in the generator's order
    assert len({s.layout for s in gen}) == 4                      # layouts cycle with the density
    assert gen[0].path == "scenes/highway/highway-benchmark-000000.json.gz"
    assert [s.recording for s in real] == [4, 6, 9]               # one scene per benchmark recording first
    assert all(s.path.startswith("scenes/real/") for s in real)
    # growing the set keeps what was chosen: the smaller set is a prefix of each part
    more = select_scenes(7, 4)
    assert [s for s in more if s.part == "generated"][:5] == gen
    assert [s for s in more if s.part == "real"][:3] == real
    assert select_scenes(0, 0) == []
    with pytest.raises(ConfigError):
        select_scenes(0, 99)
    with pytest.raises(ConfigError):
        select_scenes(-1, 0)


def test_evaluation_seeds_are_held_out_from_the_search():
    digest = "sha256:" + "ab" * 32
    seeds = evaluation_seeds(3, digest, 5)
    assert len(set(seeds)) == 5 and seeds == evaluation_seeds(3, digest, 5)
    assert scene_seed(3, digest, "search") not in seeds and scene_seed(3, digest, "noise") not in seeds
    assert seeds[0] == scene_seed(3, digest, "eval0")
    assert evaluation_seeds(3, digest, 2) == seeds[:2]           # more evaluation seeds extend the list
    assert evaluation_seeds(4, digest, 2) != seeds[:2]
    with pytest.raises(ConfigError):
        evaluation_seeds(3, digest, 0)


def test_heldout_store_round_trip_and_unit_check(tmp_path):
    path = tmp_path / "heldout.json.gz"
    store = HeldoutStore(path)
    u = np.array([0.1, 0.2, 0.3, 0.4, 0.5])
    store.put("s|closed|7", u, {"seed": 7, "cost": 1.5, "components": {}, "metrics": {}})
    store.put("s|original|7", None, {"seed": 7, "cost": -2.0, "components": {}, "metrics": {}})
    again = HeldoutStore(path)
    assert again.get("s|closed|7", u)["cost"] == 1.5
    assert again.get("s|closed|7", u + 0.01) is None              # another best shape: evaluate again
    assert again.get("s|original|7", None)["cost"] == -2.0
    assert again.get("s|original|7", u) is None and again.get("s|open|7", u) is None
    path.write_text('{"format": "something-else", "version": 1, "evaluations": {}}')
    with pytest.raises(FileFormatError):
        HeldoutStore(path)


def test_run_heldout_reuses_the_same_shape_seed_and_scene(tmp_path):
    """Open- and closed-loop searches that kept the same point need one simulation: a stored
    record of the same scene, seed and unit vector is copied, nothing is simulated."""
    from adv3d_runner.attack.config import QuerySettings

    store = HeldoutStore(tmp_path / "h.json.gz")
    u = (0.5, 0.5, 0.5, 0.5, 0.5)
    store.put("s|open|11", np.array(u), {"seed": 11, "cost": 3.0, "components": {"det": 1.0}, "metrics": {}})
    tasks = [HeldoutTask("no-such-file.json", "s", "open", u, 11), HeldoutTask("no-such-file.json", "s", "closed", u, 11)]
    done = []
    assert run_heldout(tasks, QuerySettings(), store, on_done=done.append) == 0  # the scene file is never read
    assert store.get("s|closed|11", np.array(u))["cost"] == 3.0 and [t.what for t in done] == ["closed"]


def test_metric_value_and_scene_means():
    rec = {"cost": 2.0, "metrics": {"detection": {"ap": 0.75, "recall": None}, "prediction": {"min_ade": 1.2}}}
    assert metric_value(rec, "objective") == 2.0
    assert metric_value(rec, "AP") == 75.0                         # in %
    assert np.isnan(metric_value(rec, "Recall")) and np.isnan(metric_value(rec, "Drive jerk"))
    pairs = [("a", {"cost": 1.0}), ("a", {"cost": 3.0}), ("b", {"cost": None}), ("b", {"cost": 4.0}), ("c", {})]
    means = scene_means(pairs, lambda r: metric_value(r, "objective"))
    assert means["a"] == 2.0 and means["b"] == 4.0 and np.isnan(means["c"])


def test_original_settings_drop_what_the_original_scene_never_reads():
    from dataclasses import replace

    from adv3d_runner.attack.config import QuerySettings
    from adv3d_runner.attack.protocol import original_settings

    base = QuerySettings(autonomy="oracle", seconds=2.0)
    for other in (replace(base, shape_model="vd", vd_bound=0.2), replace(base, realism_weight=300.0, class_scales=True),
                  replace(base, seed=5, scene_seeds=True), replace(base, incremental=False)):
        assert original_settings(other) == original_settings(base)
    for other in (replace(base, objective="M1"), replace(base, target_rank=1), replace(base, actors=2),
                  replace(base, reactive=True), replace(base, autonomy="A")):
        assert original_settings(other) != original_settings(base)


def test_run_heldout_shares_the_original_between_settings(tmp_path, monkeypatch):
    """A second setting of a table (another shape model, realism preset or algorithm) copies the
    original scene's held-out records this process made for the first one: nothing simulated."""
    from dataclasses import replace

    from adv3d_runner.attack import protocol
    from adv3d_runner.attack.config import QuerySettings

    monkeypatch.setattr(protocol, "_ORIGINAL_RECORDS", {})
    first = HeldoutStore(tmp_path / "a.json.gz")
    rec = {"seed": 11, "cost": 2.0, "components": {"det": 1.0}, "metrics": {}}
    tasks = [HeldoutTask(str(tmp_path / "no-such-scene.json"), "s", "original", None, 11)]
    protocol._ORIGINAL_RECORDS[protocol._original_key(tasks[0].ref, QuerySettings(), 11)] = rec
    assert run_heldout(tasks, replace(QuerySettings(), shape_model="vd"), first) == 0  # the scene file is never read
    assert first.get("s|original|11", None)["cost"] == 2.0
    second = HeldoutStore(tmp_path / "b.json.gz")
    with pytest.raises(Adv3dError, match="no-such-scene"):  # another objective: a new evaluation
        run_heldout(tasks, replace(QuerySettings(), objective="M1"), second)


def test_the_shared_original_evaluation_is_the_settings_own(tmp_path):
    """The original scene evaluated under original_settings gives the record the setting's own
    workspace gives (other search seeds, shape-model bound, plain LiDAR)."""
    from dataclasses import replace

    from adv3d_runner.attack.config import QuerySettings
    from adv3d_runner.attack.evaluator import workspace_for
    from adv3d_runner.attack.protocol import _clean, heldout_evaluate, original_settings

    scene = str(Path(__file__).resolve().parents[1] / "scenes" / "highway" / "highway-benchmark-000000.json.gz")
    settings = QuerySettings(autonomy="oracle", seconds=1.0, seed=7, scene_seeds=True, vd_bound=0.2, incremental=False)
    assert original_settings(settings) != settings
    res, _ = workspace_for(scene, settings).evaluate(None, closed_loop=True, seed=123)
    own = _clean({"seed": 123, "cost": res.cost, "components": res.components, "metrics": res.metrics})
    assert heldout_evaluate(scene, settings, None, 123) == own


def test_fresh_scenes_spread_over_recordings_and_speed_ranks():
    from adv3d_runner.attack.protocol import select_fresh
    from adv3d_runner.scene.real import load_fresh_part

    part = load_fresh_part()
    nine = select_fresh(9)
    assert [s.recording for s in nine] == list(part.recordings)   # one per fresh recording first
    assert all(s.part == "real-fresh" and s.path.startswith("scenes/real-fresh/") for s in nine)
    ranks = {}
    for row, path in zip(part.rows, part.paths()):
        ranks.setdefault(int(row["recording"]), []).append(path.name)
    # recording j's first scene is its speed rank j mod n: the first pass spreads over the ranks
    got = [ranks[s.recording].index(s.path.split("/")[-1]) for s in nine]
    assert got == [j % len(ranks[r]) for j, r in enumerate(sorted(ranks))]
    more = select_scenes(2, 0, n_fresh=12)
    assert more[:2] == select_scenes(2, 0) and more[2:11] == nine   # a larger set extends a smaller one
    assert len({s.path for s in select_fresh(len(part.rows))}) == len(part.rows)
    with pytest.raises(ConfigError, match="fresh real part holds"):
        select_fresh(len(part.rows) + 1)
