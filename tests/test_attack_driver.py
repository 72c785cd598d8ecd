"""Attack driver and run journal: resume after a crash, determinism, failed queries, CLI.

Most tests drive the machinery with the analytic :class:`attack_synthetic.SyntheticEvaluator`
(no simulator); the real-scene tests use the production episode evaluator."""
from __future__ import annotations

import json

import numpy as np
import pytest
from attack_synthetic import SyntheticEvaluator

from adv3d_runner.attack.config import AttackConfig
from adv3d_runner.attack.driver import run_attack as _run_attack
from adv3d_runner.attack.journal import Journal, query_record, read_run, strip_times
from adv3d_runner.errors import ConfigError, FileFormatError


def cfg(**kw):
    base = dict(scenes=["synthetic:peak"], algo="bo", budget=24, batch=2, n_initial=6, seed=5)
    base.update(kw)
    return AttackConfig(**base)


def run_attack(config, out, **kw):
    """``run_attack`` with the synthetic evaluator unless told otherwise."""
    kw.setdefault("evaluator", SyntheticEvaluator)
    return _run_attack(config, out, **kw)


def lines(path):
    return [json.loads(x) for x in (path / "queries.jsonl").read_text().splitlines()]


def test_same_seed_same_journal(tmp_path):
    run_attack(cfg(), tmp_path / "a", show_progress=False)
    run_attack(cfg(), tmp_path / "b", show_progress=False)
    a, b = lines(tmp_path / "a"), lines(tmp_path / "b")
    assert len(a) == 24
    assert strip_times(a) == strip_times(b)
    assert [r["index"] for r in a] == list(range(24))
    run_attack(cfg(seed=6), tmp_path / "c", show_progress=False)
    assert strip_times(lines(tmp_path / "c")) != strip_times(a)


def test_failed_queries_recorded_and_run_continues(tmp_path):
    # random search over the unit cube hits the synthetic invalid regions (u0 or u1 > 0.95)
    run_attack(cfg(algo="random", budget=80), tmp_path / "r", show_progress=False)
    recs = lines(tmp_path / "r")
    assert len(recs) == 80
    status = {r["status"] for r in recs}
    assert {"ok", "invalid", "error"} <= status
    for r in recs:
        if r["status"] != "ok":
            assert r["cost"] is None and r["error"]
        else:
            assert isinstance(r["cost"], float)
    inv = [r for r in recs if r["status"] == "invalid"]
    assert all("EmptySurfaceError" in r["error"] for r in inv)
    summary = json.loads((tmp_path / "r" / "summary.json").read_text())
    m = summary["scenes"]["synthetic:peak"]["modes"]["closed"]
    ok = [r["cost"] for r in recs if r["status"] == "ok"]
    assert m["best_cost"] == pytest.approx(max(ok))
    assert m["n_failed"] == sum(r["status"] != "ok" for r in recs)


@pytest.mark.parametrize("algo", ["bo", "random", "grid", "blendsearch", "skopt"])
def test_resume_after_crash_does_not_redo_queries(tmp_path, algo):
    if algo == "blendsearch":
        pytest.importorskip("flaml")
        pytest.importorskip("optuna")
    budget, stop = 24, 10
    if algo == "skopt":  # a GP hyper-parameter fit per tell: a shorter run past its 4 initial points
        pytest.importorskip("skopt")
        budget, stop = 12, 6

    def config():
        return cfg(algo=algo, budget=budget, n_initial=4) if algo == "skopt" else cfg(algo=algo)

    full = tmp_path / "full"
    run_attack(config(), full, show_progress=False)
    crashed = tmp_path / "crashed"
    run_attack(config(), crashed, show_progress=False, stop_after=stop)
    journal = crashed / "queries.jsonl"
    done = journal.read_text().splitlines()
    assert len(done) == stop
    # kill -9 in the middle of a write: a truncated last line
    with open(journal, "a") as fh:
        fh.write(done[-1][: len(done[-1]) // 2])
    calls = []

    class Counting(SyntheticEvaluator):
        def evaluate(self, query):
            calls.append(query.unit.tolist())
            return super().evaluate(query)

    run_attack(config(), crashed, show_progress=False, evaluator=Counting)
    assert len(calls) == budget - stop  # only the queries that were not in the journal
    assert strip_times(lines(crashed)) == strip_times(lines(full))
    # a second resume of a finished run evaluates nothing
    calls.clear()
    run_attack(config(), crashed, show_progress=False, evaluator=Counting)
    assert calls == []
    assert len(lines(crashed)) == budget


def test_resume_with_other_options_refused(tmp_path):
    run_attack(cfg(budget=4), tmp_path / "x", show_progress=False)
    with pytest.raises(ConfigError):
        run_attack(cfg(budget=4, seed=99), tmp_path / "x", show_progress=False)
    # workers may change on resume (the first run's batch size is kept)
    run_attack(cfg(budget=6, batch=2), tmp_path / "y", show_progress=False)
    with pytest.raises(ConfigError):
        run_attack(cfg(budget=6, batch=3), tmp_path / "y", show_progress=False)


def test_kill_during_a_batch_on_two_workers_then_resume_on_one(tmp_path, monkeypatch):
    """Two worker processes, batches of 4, stopped (as if killed) after 5 results: every
    result the driver had is journalled (queries.jsonl or the pending file), and so is the query
    still running at the stop, which its worker wrote to the pending file itself when it finished
    (driver.durable_query); the resume, with another worker count, evaluates only the queries
    that were never journalled, and the run ends with the serial run's journal."""
    from attack_synthetic import SyntheticLogged

    c = cfg(algo="random", budget=8, batch=4, seed=2)  # query 5 takes 80 ms less than query 4
    run_attack(c, tmp_path / "serial", show_progress=False)
    monkeypatch.setenv("ADV3D_TEST_EVAL_LOG", str(tmp_path / "killed.log"))
    run_attack(c, tmp_path / "run", workers=2, stop_after=5, evaluator=SyntheticLogged, show_progress=False)
    j = Journal(tmp_path / "run")
    j.load()
    journalled = j.records + list(j.pending.values())
    # batch 1 in the journal; of batch 2 (4 and 5 running), 5 finished first: in the pending
    # file, and 4, finished by its worker after the driver stopped, after it
    assert [r["index"] for r in j.records] == [0, 1, 2, 3] and [k[2] for k in j.pending] == [5, 4]
    assert json.loads((tmp_path / "run" / "run.json").read_text())["batch"] == 4
    monkeypatch.setenv("ADV3D_TEST_EVAL_LOG", str(tmp_path / "resumed.log"))
    run_attack(c, tmp_path / "run", workers=1, evaluator=SyntheticLogged, show_progress=False)
    redone = [json.loads(x) for x in (tmp_path / "resumed.log").read_text().splitlines()]
    done_units = [np.ravel(r["unit"]).tolist() for r in journalled]
    assert len(redone) == 8 - 6  # 6, 7
    assert not any(np.allclose(u, d, rtol=0, atol=1e-12) for u in redone for d in done_units)
    assert strip_times(lines(tmp_path / "run")) == strip_times(lines(tmp_path / "serial"))
    assert (tmp_path / "run" / "queries.pending.jsonl").read_bytes() == b""


def test_workers_give_the_same_journal(tmp_path):
    run_attack(cfg(budget=12), tmp_path / "serial", workers=1, show_progress=False)
    run_attack(cfg(budget=12), tmp_path / "pool", workers=2, show_progress=False)
    assert strip_times(lines(tmp_path / "serial")) == strip_times(lines(tmp_path / "pool"))


def test_scenes_run_concurrently_and_the_journal_does_not_depend_on_workers(tmp_path, monkeypatch):
    """Three scenes x two modes, one query asked at a time: two workers both evaluate queries
    (the searches run concurrently), and the finished run's journal, summary and best-shape
    files are the serial run's, byte for byte up to wall times."""
    from attack_synthetic import SyntheticWithBest

    scenes = ["synthetic:peak", "synthetic:bowl", "synthetic:ridge"]
    c = cfg(scenes=scenes, mode="both", budget=6, batch=1, n_initial=3)
    run_attack(c, tmp_path / "serial", workers=1, show_progress=False, evaluator=SyntheticWithBest)
    pids = tmp_path / "pids"
    pids.mkdir()
    monkeypatch.setenv("ADV3D_TEST_PID_DIR", str(pids))
    run_attack(c, tmp_path / "pool", workers=2, show_progress=False, evaluator=SyntheticWithBest)
    assert len(list(pids.iterdir())) == 2  # both workers evaluated queries

    def text(run, name):
        return (tmp_path / run / name).read_text()

    def strip(line):
        return line[:line.rindex(',"wall_s"')]

    serial, pool = (text(r, "queries.jsonl").splitlines() for r in ("serial", "pool"))
    assert len(serial) == 3 * 2 * 6 and [strip(x) for x in serial] == [strip(x) for x in pool]
    assert [(r["scene"], r["mode"]) for r in lines(tmp_path / "pool")][::6] == \
        [(s, m) for s in scenes for m in ("open", "closed")]
    a, b = (json.loads(text(r, "summary.json")) for r in ("serial", "pool"))
    a.pop("wall_s"), b.pop("wall_s")
    assert a == b and list(b["scenes"]) == scenes and list(b["scenes"]["synthetic:bowl"]["modes"]) == ["open", "closed"]
    assert all("original" in e and e["modes"]["closed"]["closed_loop_eval"] for e in b["scenes"].values())
    for s in ("peak", "bowl", "ridge"):
        for m in ("open", "closed"):
            f = f"scenes/synthetic:{s}/{m}/best.txt"
            assert text("serial", f) == text("pool", f)


def test_journal_canonical_order_after_a_resume(tmp_path):
    """A run stopped part-way and resumed ends with the journal of an uninterrupted run."""
    c = cfg(scenes=["synthetic:peak", "synthetic:bowl"], budget=6, batch=1, n_initial=3)
    run_attack(c, tmp_path / "full", show_progress=False)
    run_attack(c, tmp_path / "part", show_progress=False, stop_after=8)
    # as a run with several workers leaves it: lines in completion order, not canonical
    path = tmp_path / "part" / "queries.jsonl"
    path.write_text("".join(reversed(path.read_text().splitlines(keepends=True))))
    run_attack(c, tmp_path / "part", show_progress=False)
    assert strip_times(lines(tmp_path / "part")) == strip_times(lines(tmp_path / "full"))


def test_journal_corrupt_middle_line_is_an_error(tmp_path):
    j = Journal(tmp_path)
    j.start({"seed": 0})
    for i in range(3):
        j.append(query_record("s", "closed", i, [1], np.full(5, 0.5), cost=float(i)))
    text = (tmp_path / "queries.jsonl").read_text().splitlines()
    text[1] = "{not json"
    (tmp_path / "queries.jsonl").write_text("\n".join(text) + "\n")
    with pytest.raises(FileFormatError):
        Journal(tmp_path).load()
    with pytest.raises(FileFormatError):
        read_run(tmp_path)


def test_journal_nonfinite_cost_written_as_null(tmp_path):
    j = Journal(tmp_path)
    j.start({"seed": 0})
    j.append(query_record("s", "closed", 0, [1], np.full(5, 0.5), cost=float("nan"), status="error", error="x"))
    rec = json.loads((tmp_path / "queries.jsonl").read_text())
    assert rec["cost"] is None and rec["status"] == "error"


def test_cli_attack_and_report(tmp_path, repo_root, capsys, monkeypatch):
    from adv3d_runner.cli import main

    scene = repo_root / "scenes" / "highway" / "highway-benchmark-000000.json.gz"
    if not scene.exists():
        pytest.skip("no bundled scenes")
    out = tmp_path / "run"
    assert main(["-q", "attack", str(scene), "--algo", "random", "--budget", "2", "--seconds", "0.3",
                 "--autonomy", "oracle", "--out", str(out)]) == 0
    assert len(lines(out)) == 2
    run = json.loads((out / "run.json").read_text())
    assert run["scenes"] == [str(scene)] and run["autonomy"] == "oracle" and run["seconds"] == 0.3
    assert AttackConfig.from_run_json(run) == AttackConfig([str(scene)], algo="random", budget=2, seconds=0.3,
                                                          autonomy="oracle", region="realistic")  # the CLI's default
    # resuming: --workers may change, --batch is kept from run.json (a different one is refused)
    before = (out / "queries.jsonl").read_text()
    assert main(["-q", "attack", str(scene), "--algo", "random", "--budget", "2", "--seconds", "0.3",
                 "--autonomy", "oracle", "--workers", "2", "--out", str(out)]) == 0
    assert (out / "queries.jsonl").read_text() == before
    capsys.readouterr()
    assert main(["-q", "attack", str(scene), "--algo", "random", "--budget", "2", "--seconds", "0.3",
                 "--autonomy", "oracle", "--batch", "2", "--out", str(out)]) == 1
    err = capsys.readouterr().err
    assert "--batch 1 (run.json field 'batch')" in err and "asks --batch 2" in err
    # the same scene by a relative path is the same run: a killed run (its last query lost)
    # resumes from it, on two workers, and ends with the same journal
    monkeypatch.chdir(repo_root)
    rel = str(scene.relative_to(repo_root))
    (out / "queries.jsonl").write_text(before.splitlines(keepends=True)[0])
    assert main(["-q", "attack", rel, "--algo", "random", "--budget", "2", "--seconds", "0.3",
                 "--autonomy", "oracle", "--workers", "2", "--out", str(out)]) == 0
    assert strip_times(lines(out)) == strip_times([json.loads(x) for x in before.splitlines()])
    assert main(["-q", "attack", rel, "--algo", "random", "--budget", "3", "--seconds", "0.3",
                 "--autonomy", "oracle", "--out", str(out)]) == 1  # another budget is another run
    assert "(budget)" in capsys.readouterr().err
    assert main(["-q", "report", str(out)]) == 0
    text = (out / "report.md").read_text()
    assert "highway-benchmark-000000" in text and "random" in text
    assert (out / "convergence.png").exists()
    with pytest.raises(SystemExit) as exc:  # refused by the argument type: one usage line, exit 2
        main(["-q", "attack", str(scene), "--budget", "0", "--out", str(tmp_path / "z")])
    assert exc.value.code == 2 and not (tmp_path / "z").exists()


def test_report_of_a_run_without_closed_loop_evaluations(tmp_path):
    from adv3d_runner.attack.report import write_report

    run_attack(cfg(algo="random", budget=8), tmp_path / "run", show_progress=False)
    text = write_report([tmp_path / "run"]).read_text()
    assert "synthetic:peak" in text and "No closed-loop evaluations" in text
    assert not list((tmp_path / "run").glob("thumb_*.png"))  # nothing was simulated: no shapes to show


@pytest.mark.slow
def test_ray_local_instance_same_journal(tmp_path, monkeypatch):
    """Queries evaluated as Ray tasks on a local Ray instance give the serial journal."""
    ray = pytest.importorskip("ray")
    monkeypatch.setenv("RAY_USAGE_STATS_ENABLED", "0")
    ray.init(num_cpus=1, include_dashboard=False, log_to_driver=False, namespace="adv3d-test")
    try:
        address = ray.get_runtime_context().gcs_address
        run_attack(cfg(budget=8), tmp_path / "ray", ray_address=address, show_progress=False)
    finally:
        ray.shutdown()
    run_attack(cfg(budget=8), tmp_path / "serial", show_progress=False)
    assert strip_times(lines(tmp_path / "ray")) == strip_times(lines(tmp_path / "serial"))
    assert json.loads((tmp_path / "ray" / "run.json").read_text())["ray_address"] == address


def test_real_scene_short_attack_bundle(tmp_path, repo_root, monkeypatch):
    """A 2-query, 1 s closed-loop attack on a bundled scene with oracle perception: costs and
    metrics journalled, an invalid shape (no surface) recorded without stopping the run, the
    best shape's glb and replay written and loadable."""
    scene = repo_root / "scenes" / "highway" / "highway-benchmark-000000.json.gz"
    if not scene.exists():
        pytest.skip("no bundled scenes")
    from adv3d_runner.attack import evaluator
    from adv3d_runner.errors import EmptySurfaceError
    from adv3d_runner.shapes.shape_space import ShapeSpace
    from adv3d_runner.sim.replay import load_replay

    real = ShapeSpace.decode_latent
    calls = []

    def flaky(self, z, scales=(1.0, 1.0)):
        calls.append(1)
        if len(calls) == 2:  # the second query has "no surface"
            raise EmptySurfaceError("test: no surface")
        return real(self, z, scales)

    monkeypatch.setattr(ShapeSpace, "decode_latent", flaky)
    monkeypatch.setattr(evaluator, "_WORKSPACES", {})
    c = AttackConfig([str(scene)], algo="random", budget=3, seconds=1.0, autonomy="oracle", seed=1)
    summary = _run_attack(c, tmp_path / "run", show_progress=False)
    recs = lines(tmp_path / "run")
    assert [r["status"] for r in recs] == ["ok", "invalid", "ok"]
    ok = recs[0]
    assert np.isfinite(ok["cost"]) and ok["metrics"]["detection"]["n_gt"] >= 0
    assert ok["components"]["frames"] == 10 and len(ok["dimensions"][0]) == 3
    entry = summary["scenes"]["highway-benchmark-000000"]
    m = entry["modes"]["closed"]
    assert m["best_cost"] == pytest.approx(max(r["cost"] for r in recs if r["status"] == "ok"))
    assert "original" in entry and m["closed_loop_eval"]["cost"] == pytest.approx(m["best_cost"])
    aid = entry["targets"][0]
    assert (tmp_path / "run" / m["files"]["meshes"][str(aid)]).exists()
    rp = load_replay(tmp_path / "run" / m["files"]["replay"], points=False)
    assert rp.n_frames == 10 and any(a.adversarial for a in rp.actors)


def test_autonomy_b_short_attack_bundle_and_report(tmp_path, repo_root, monkeypatch):
    """The Table 1 lower-block campaign on a tiny budget: 2 queries, 0.5 s, closed loop, against
    Autonomy-B. B's objective terms are journalled, the occupancy model's fingerprint is in
    run.json, the best shape's replay carries heat maps and the report has the lower block."""
    scene = repo_root / "scenes" / "highway" / "highway-benchmark-000000.json.gz"
    if not (repo_root / "assets" / "models" / "occupancy" / "config.json").is_file():
        pytest.skip("no shipped occupancy model")
    from adv3d_runner.attack import evaluator
    from adv3d_runner.attack.report import write_report
    from adv3d_runner.sim.replay import load_replay

    monkeypatch.setattr(evaluator, "_WORKSPACES", {})
    c = AttackConfig([str(scene)], algo="bo", budget=2, n_initial=2, mode="closed", seconds=0.5, autonomy="B", seed=0)
    summary = _run_attack(c, tmp_path / "run", show_progress=False)
    recs = lines(tmp_path / "run")
    assert len(recs) == 2 and all(r["status"] == "ok" for r in recs)
    assert set(recs[0]["components"]) == {"det", "soft_iou", "pred", "plan", "frames"}
    assert recs[0]["metrics"]["detection"] is None and recs[0]["metrics"]["occupancy"]["n_queries"] > 0
    assert recs[0]["cost"] == pytest.approx(-recs[0]["components"]["soft_iou"] + 1.0 * recs[0]["components"]["pred"]
                                            + 0.5 * recs[0]["components"]["plan"])
    run = json.loads((tmp_path / "run" / "run.json").read_text())
    assert run["autonomy"] == "B" and set(run["versions"]["models"]) == {"occupancy"}
    m = summary["scenes"]["highway-benchmark-000000"]["modes"]["closed"]
    rp = load_replay(tmp_path / "run" / m["files"]["replay"], points=False)
    assert all(f.occupancy is not None for f in rp.frames)
    text = write_report([tmp_path / "run"]).read_text()
    assert "Closed-loop evaluation of Autonomy-B (paper Table 1, lower block)" in text and "Occ. mAP" in text


def test_scene_without_targets_is_skipped(tmp_path):
    class NoTargets(SyntheticEvaluator):
        def targets(self, ref):
            if ref == "synthetic:empty":
                raise ConfigError("no actor in front of the ego")
            return super().targets(ref)

    s = run_attack(cfg(scenes=["synthetic:empty", "synthetic:peak"], budget=4), tmp_path / "s",
                   show_progress=False, evaluator=NoTargets)
    assert "skipped" in s["scenes"]["synthetic:empty"]
    assert {r["scene"] for r in lines(tmp_path / "s")} == {"synthetic:peak"}  # the next scene still ran


def test_run_records_the_library_fingerprint_and_a_resume_checks_it(tmp_path):
    """run.json (version 2) records the vehicle library's fingerprint; a resume with another
    library, or of a version 1 run (made before fingerprints), is refused; v1 runs still read."""
    import json

    from adv3d_runner.attack.config import library_fingerprint_of
    from adv3d_runner.attack.journal import read_run
    from adv3d_runner.errors import ConfigError

    out = tmp_path / "run"
    cfg = AttackConfig(scenes=("a", "b"), algo="random", budget=3, seed=1)
    run_attack(cfg, out, evaluator=SyntheticEvaluator, show_progress=False)
    run = json.loads((out / "run.json").read_text())
    assert run["version"] == 2 and run["library"] is None
    assert run["library_fingerprint"] == library_fingerprint_of(None) and run["library_fingerprint"].startswith("sha256:")
    run_attack(cfg, out, evaluator=SyntheticEvaluator, show_progress=False)  # same library: resumes
    with pytest.raises(ConfigError, match="another vehicle library"):
        run_attack(AttackConfig(scenes=("a", "b"), algo="random", budget=3, seed=1, library="none"), out,
                   evaluator=SyntheticEvaluator, show_progress=False)
    run["version"] = 1
    del run["library"], run["library_fingerprint"]
    (out / "run.json").write_text(json.dumps(run))
    assert read_run(out)[0]["version"] == 1  # a v1 run is still read (reports)
    with pytest.raises(ConfigError, match="version 1"):
        run_attack(cfg, out, evaluator=SyntheticEvaluator, show_progress=False)


class _TwoPeaks(SyntheticEvaluator):
    """Scenes ``synthetic:peak#N``: the same analytic scene under distinct ids and contents."""

    def evaluate(self, query):
        from dataclasses import replace as _replace

        return super().evaluate(_replace(query, scene=query.scene.split("#")[0]))


def test_scene_seeds_give_each_scene_its_own_search(tmp_path):
    from adv3d_runner.attack.config import scene_seed

    scenes = ["synthetic:peak#1", "synthetic:peak#2"]
    run_attack(cfg(scenes=scenes, algo="random", budget=5), tmp_path / "same", evaluator=_TwoPeaks,
               show_progress=False)
    recs = lines(tmp_path / "same")
    units = {s: [r["unit"] for r in recs if r["scene"] == s] for s in scenes}
    assert units[scenes[0]] == units[scenes[1]]  # default: one search sequence for every scene
    run_attack(cfg(scenes=scenes, algo="random", budget=5, scene_seeds=True), tmp_path / "own",
               evaluator=_TwoPeaks, show_progress=False)
    recs = lines(tmp_path / "own")
    units = {s: [r["unit"] for r in recs if r["scene"] == s] for s in scenes}
    assert units[scenes[0]] != units[scenes[1]]
    summary = json.loads((tmp_path / "own" / "summary.json").read_text())
    for s in scenes:
        m = summary["scenes"][s]["modes"]["closed"]
        assert m["search_seed"] == scene_seed(5, s, "search") and m["noise_seed"] == scene_seed(5, s, "noise")
        # the recorded search seed reproduces the scene's sequence
        rng_units = np.random.default_rng(m["search_seed"]).random((5, 5))
        assert np.allclose(np.reshape(units[s], (5, 5)), rng_units)
    assert summary["run"]["scene_seeds"] is True and summary["run"]["pred_reduction"] == "sum"
    _run, _recs, read = read_run(tmp_path / "own")  # the seeds pass summary.json's validation
    assert read["scenes"][scenes[0]]["modes"]["closed"]["search_seed"] == scene_seed(5, scenes[0], "search")


def test_resume_under_other_versions_says_so(tmp_path, capsys, monkeypatch):
    """A run resumed by other code (here: another planner fingerprint) keeps its journalled
    queries, and says that it does."""
    from adv3d_runner import progress

    monkeypatch.setattr(progress, "_QUIET", False)  # status lines are printed (other tests may set quiet)
    out = tmp_path / "run"
    run_attack(cfg(budget=4), out, show_progress=False)
    capsys.readouterr()
    run_attack(cfg(budget=4), out, show_progress=False)
    assert "other versions" not in capsys.readouterr().out
    doc = json.loads((out / "run.json").read_text())
    doc["versions"] = {**doc["versions"], "planner": "0000000000000000"}
    (out / "run.json").write_text(json.dumps(doc))
    run_attack(cfg(budget=4), out, show_progress=False)
    said = capsys.readouterr().out
    assert "other versions" in said and "planner: 0000000000000000 ->" in said
