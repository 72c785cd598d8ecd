"""Realism in the attack (docs/realism.md): the cheap per-query figures, the restricted
search region (Mahalanobis ball, class-plausible scales), the realism penalty, the
vertex-deformation baseline, their options in AttackConfig / run.json / the CLI, and the
journal, summary and report that carry the figures."""
from __future__ import annotations

import json

import numpy as np
import pytest
from attack_synthetic import SyntheticEvaluator

from adv3d_runner.attack.config import AttackConfig, QuerySettings
from adv3d_runner.attack.driver import run_attack
from adv3d_runner.attack.realism_constraints import (
    LatentRegion, plausible_scale_range, preset_knobs, realism_penalty)
from adv3d_runner.attack.vertex_deform import VertexDeformation, lattice_dim, lattice_weights
from adv3d_runner.errors import ConfigError
from adv3d_runner.shapes import realism as R
from adv3d_runner.shapes.shape_space import DEFAULT_SHAPE_SPACE, ShapeSpace
from adv3d_runner.vehicle_classes import DIMENSION_RANGES

SCENE = "scenes/highway/highway-benchmark-000000.json.gz"
BLOB_U = [1.0, 0.6458, 0.0, 0.0, 0.0]  # the BO corner of scene 000000 (docs/realism.md)


@pytest.fixture(scope="module")
def space():
    if not DEFAULT_SHAPE_SPACE.exists():
        pytest.skip("no shipped shape space")
    return ShapeSpace.load()


@pytest.fixture(scope="module")
def ref(space):
    return R.default_reference(space)


def lines(root) -> list[dict]:
    return [json.loads(x) for x in (root / "queries.jsonl").read_text().splitlines()]


# ----------------------------------------------------------------------------- cheap figures

def test_quick_measures_agree_with_the_full_report(space, ref):
    for u in (BLOB_U, space.asset_unit("kenney-car-kit.sedan")):
        z, sc = space.unit_to_latent(u)
        v, f = space.decode_latent(z, sc)
        full = R.realism_report(space, u, ref, vehicle_class="sedan")
        quick = R.quick_measures(v, f, ref, latent=z, latents=space.latents, vehicle_class="sedan")
        for key in ("jsd", "nearest_asset", "nearest_chamfer_m", "mahalanobis", "dimension_excess", "dimensions_m"):
            assert quick[key] == full[key], key
        assert set(quick["flags"]) == set(full["flags"]) & {"jsd", "nearest_chamfer_m", "mahalanobis", "dimension_excess"}
    blob = R.quick_measures(*space.decode_arrays(BLOB_U), ref, vehicle_class="sedan")
    # with the v2 reference (28 vehicles) the blob's JSD stays inside the library's range: its size flags it
    assert "dimension_excess" in blob["flags"] and "mahalanobis" not in blob
    live = R.quick_measures(*space.decode_arrays(BLOB_U), ref, latent=space.unit_to_latent(BLOB_U)[0],
                            latents=space.latents, chamfer=False)
    assert "nearest_asset" not in live and live["jsd"] == blob["jsd"]
    assert live["dimension_class"] is not None  # the nearest latent's class stands in
    assert R.quick_measures(*space.decode_arrays(BLOB_U), ref, chamfer=False)["dimension_excess"] is None


# ----------------------------------------------------------------------------- region

def test_latent_region_maps_the_cube_onto_the_ball_inside_the_box(space):
    rng = np.random.default_rng(0)
    for radius in (0.5, 2.0, 3.37, 50.0):
        region = LatentRegion.from_space(space, radius)
        np.testing.assert_allclose(region.to_latent(np.full(space.k, 0.5)), space.latents.mean(axis=0))
        U = rng.random((300, space.k))
        Z = np.array([region.to_latent(u) for u in U])
        maha = np.array([R.latent_mahalanobis(z, space.latents) for z in Z])
        assert maha.max() <= radius + 1e-9
        assert np.all(Z >= space.latent_min - 1e-12) and np.all(Z <= space.latent_max + 1e-12)
        # along a ray the distance grows linearly with the l-infinity norm of 2u - 1
        d = rng.normal(size=space.k)
        d /= np.abs(d).max()
        m = [R.latent_mahalanobis(region.to_latent(0.5 + 0.5 * t * d), space.latents) for t in (0.25, 0.5, 1.0)]
        np.testing.assert_allclose(np.array(m) / m[-1], [0.25, 0.5, 1.0], atol=1e-9)
    small = LatentRegion.from_space(space, 0.5)  # inside the box: the cube's surface is the sphere
    for u in rng.random((20, space.k)):
        u[0] = 1.0
        assert R.latent_mahalanobis(small.to_latent(u), space.latents) == pytest.approx(0.5)
    big = LatentRegion.from_space(space, 50.0)  # the box bounds it: some corner of the box is reached
    assert np.any(np.isclose(big.to_latent(np.ones(space.k)), space.latent_max))
    for bad in (0.0, -1.0, float("inf")):
        with pytest.raises(ConfigError):
            LatentRegion.from_space(space, bad)


def test_plausible_scale_range():
    assert plausible_scale_range(4.0, (4.0, 5.4), (0.8, 1.3)) == (1.0, 1.3)
    lo, hi = plausible_scale_range(1.5, (1.65, 1.97), (0.8, 1.3))
    assert lo == pytest.approx(1.1) and hi == 1.3                                # capped by the space
    lo, hi = plausible_scale_range(1.7, (1.65, 1.97), (0.8, 1.3))
    assert lo == pytest.approx(1.65 / 1.7)
    assert hi == pytest.approx(1.97 / 1.7)
    assert plausible_scale_range(1.0, (1.65, 1.97), (0.8, 1.3)) == (1.3, 1.3)   # out of reach: closest
    assert plausible_scale_range(3.0, (1.65, 1.97), (0.8, 1.3)) == (0.8, 0.8)


def test_class_scales_keep_the_actor_within_its_class(space):
    from adv3d_runner.attack.shape_models import ActorShapes
    from adv3d_runner.scene.schema import load_scene

    scene = load_scene(SCENE)
    shapes = ActorShapes(QuerySettings(class_scales=True), scene, [3], space)
    assert shapes.classes == ["sedan"]
    (l_lo, l_hi), (w_lo, w_hi), _ = DIMENSION_RANGES["sedan"]
    rng = np.random.default_rng(1)
    for u in [np.array(BLOB_U)] + list(rng.random((8, 5))):
        v, f, z, sc = shapes.decode_actor(0, u)
        d = v.max(axis=0) - v.min(axis=0)
        base = space.decode_latent(z)[0]
        base_d = base.max(axis=0) - base.min(axis=0)
        for axis, (lo, hi), s in ((0, (l_lo, l_hi), sc[1]), (1, (w_lo, w_hi), sc[0])):
            reachable = base_d[axis] * 0.8 <= hi and base_d[axis] * 1.3 >= lo
            if reachable:
                assert lo - 1e-9 <= d[axis] <= hi + 1e-9
        ref_v, _ = space.decode_latent(z, sc)  # the same mesh as the shape space's own scaling
        np.testing.assert_allclose(v, ref_v, atol=1e-9)
        assert v[:, 2].min() == pytest.approx(0.0)
    # the blob corner of the unrestricted box (1.3 m wide) becomes a sedan-wide car
    _, _, _, sc = shapes.decode_actor(0, np.array(BLOB_U))
    assert sc[0] > 0.8


def test_realistic_preset_is_what_the_sweep_selected(repo_root):
    """The preset is the setting bench/realism_sweep.py selected, once the campaign's result is
    kept (bench/results/realism_sweep.json; the smoke run does not count)."""
    from adv3d_runner.attack.realism_constraints import PRESETS

    path = repo_root / "bench" / "results" / "realism_sweep.json"
    if not path.exists():
        pytest.skip("the sweep campaign has not been run yet (docs/realism.md)")
    doc = json.loads(path.read_text())
    assert not doc["smoke"]
    knobs = {"max_mahalanobis": None, "class_scales": False, "realism_weight": 0.0, **doc["selected_knobs"]}
    assert PRESETS["realistic"] == knobs


def test_realism_penalty_is_the_jsd_excess():
    assert realism_penalty([{"jsd": 0.5}], 0.55) == 0.0
    assert realism_penalty([{"jsd": 0.6}, {"jsd": 0.65}], 0.55) == pytest.approx(0.05 + 0.10)
    assert preset_knobs("realistic")["class_scales"] is True
    with pytest.raises(ConfigError):
        preset_knobs("nonsense")


# ----------------------------------------------------------------------------- vertex deformation

def test_lattice_weights_are_a_partition_of_unity():
    rng = np.random.default_rng(0)
    v = rng.random((500, 3)) * [4.5, 1.8, 1.5]
    nodes, w = lattice_weights(v, (6, 3, 3), v.min(axis=0), v.max(axis=0))
    assert nodes.min() >= 0 and nodes.max() < 54 and np.all(w >= -1e-15)
    np.testing.assert_allclose(w.sum(axis=1), 1.0)
    # the lattice reproduces linear functions exactly (trilinear interpolation)
    grid = np.stack(np.meshgrid(*[np.linspace(v.min(0)[i], v.max(0)[i], n) for i, n in enumerate((6, 3, 3))],
                                indexing="ij"), axis=-1).reshape(-1, 3)
    np.testing.assert_allclose(np.einsum("vc,vcd->vd", w, grid[nodes]), v, atol=1e-12)
    assert lattice_dim((6, 3, 3)) == 162
    for bad in ((1, 3, 3), (6, 3), (2.5, 2, 2)):
        with pytest.raises(ConfigError):
            lattice_dim(bad)


def test_vertex_deformation_bound_and_identity():
    import trimesh

    box = trimesh.creation.box(extents=(4.5, 1.8, 1.5))
    box = box.subdivide().subdivide()
    v = np.asarray(box.vertices) + [0, 0, 0.75]
    vd = VertexDeformation(v, box.faces, bound=0.2)
    assert vd.dim == 162
    np.testing.assert_allclose(vd.deform(np.full(vd.dim, 0.5)), v, atol=1e-12)
    rng = np.random.default_rng(0)
    for _ in range(5):
        u = rng.random(vd.dim)
        d = vd.displacements(u)
        assert np.abs(d).max() <= 0.2 + 1e-12
        out = vd.deform(u)
        assert out[:, 2].min() == pytest.approx(0.0)
        mn, mx = out.min(axis=0), out.max(axis=0)
        np.testing.assert_allclose((mn[:2] + mx[:2]) / 2, 0.0, atol=1e-12)
    # a box corner sits on a lattice node: it moves by exactly the bound
    corner = np.argmin(np.linalg.norm(v - v.max(axis=0), axis=1))
    assert np.abs(vd.displacements(np.ones(vd.dim))[corner]).max() == pytest.approx(0.2)
    with pytest.raises(ConfigError):
        VertexDeformation(v, box.faces, bound=0.0)


def test_vd_template_is_the_actors_own_mesh(space, ref):
    from adv3d_runner.attack.shape_models import ActorShapes, own_meshes
    from adv3d_runner.scene.schema import load_scene

    scene = load_scene(SCENE)
    shapes = ActorShapes(QuerySettings(shape_model="vd", vd_bound=1.0), scene, [3], space)
    assert shapes.per_actor == 162
    (v0, f0), = own_meshes(scene, [3])
    overrides, info = shapes.decode_query(np.full(162, 0.5))
    np.testing.assert_allclose(overrides[3].vertices, v0)
    actor = next(a for a in scene.actors if a.id == 3)
    np.testing.assert_allclose(overrides[3].dimensions, actor.dimensions, atol=1e-6)
    assert info["latent"] is None and info["scales"] is None
    fig = shapes.figures(overrides, info)[0]
    assert "mahalanobis" not in fig and fig["dimension_class"] == "sedan" and fig["jsd"] < ref.jsd_limit
    u = np.random.default_rng(3).random(162)
    rep = shapes.full_reports(u)[0]
    assert 0 < rep["max_displacement_m"] <= 1.0 and rep["jsd"] == shapes.figures(*shapes.decode_query(u))[0]["jsd"]
    # the limits a vertex-deformed shape's report states are the ones its flags were checked on
    assert rep["limits"]["jsd"] == R.LIMITS.resolve(ref, 0.0)["jsd"]
    assert ("jsd" in rep["flags"]) == (rep["jsd"] > rep["limits"]["jsd"])


# ----------------------------------------------------------------------------- config, CLI, journal

def test_config_knobs_round_trip_and_old_run_json():
    base = AttackConfig(["a.json.gz"])
    assert "shape_model" not in base.run_json() and "vd_bound" not in base.run_json()
    vd = AttackConfig(["a.json.gz"], shape_model="vd", vd_bound=0.2, vd_lattice=[4, 3, 2], realism_weight=50.0)
    doc = vd.run_json()
    assert doc["shape_model"] == "vd" and doc["vd_bound"] == 0.2 and doc["vd_lattice"] == [4, 3, 2]
    assert doc["realism_weight"] == 50.0 and "max_mahalanobis" not in doc
    assert AttackConfig.from_run_json(json.loads(json.dumps(doc))) == vd
    region = AttackConfig(["a.json.gz"], max_mahalanobis=3.0, class_scales=True)
    assert AttackConfig.from_run_json(json.loads(json.dumps(region.run_json()))) == region
    assert region.settings.max_mahalanobis == 3.0 and region.settings.class_scales
    hash(vd.settings)
    for bad in (dict(shape_model="mesh"), dict(shape_model="vd", algo="grid"), dict(shape_model="vd", algo="bruteforce"),
                dict(shape_model="vd", max_mahalanobis=3.0), dict(shape_model="vd", vd_bound=0.0),
                dict(algo="bruteforce", class_scales=True), dict(realism_weight=-1.0), dict(max_mahalanobis=0.0),
                dict(vd_lattice=(1, 2, 2))):
        with pytest.raises(ConfigError):
            AttackConfig(["a.json.gz"], **bad)


def test_cli_preset_and_explicit_knobs():
    import argparse

    from adv3d_runner.attack import cli

    parser = argparse.ArgumentParser()
    cli.register(parser.add_subparsers())
    args = parser.parse_args(["attack", "s.json.gz", "--out", "x", "--realism-preset", "realistic",
                              "--realism-weight", "7"])
    opts = cli._shape_options(args)
    assert opts["realism_weight"] == 7.0 and opts["class_scales"] == preset_knobs("realistic")["class_scales"]
    args = parser.parse_args(["attack", "s.json.gz", "--out", "x", "--shape-model", "vd", "--vd-bound", "0.1",
                              "--vd-lattice", "4,3,2"])
    assert cli._shape_options(args) == {"shape_model": "vd", "region": "paper", "vd_bound": 0.1,
                                        "vd_lattice": (4, 3, 2)}
    with pytest.raises(ConfigError):
        cli._shape_options(parser.parse_args(["attack", "s.json.gz", "--out", "x", "--vd-bound", "0.1"]))


def test_journal_without_realism_still_resumes(tmp_path):
    cfg = AttackConfig(["synthetic:peak"], algo="bo", budget=6, n_initial=3, seed=1)
    run_attack(cfg, tmp_path / "r", show_progress=False, evaluator=SyntheticEvaluator)
    recs = lines(tmp_path / "r")
    assert all("realism" in r and r["realism"] is None for r in recs)
    # a journal from before the realism figures (so also before checksums: run.json without journal_sha256)
    old = [{k: v for k, v in r.items() if k not in ("realism", "sha256")} for r in recs]
    (tmp_path / "r" / "queries.jsonl").write_text("".join(json.dumps(r) + "\n" for r in old))
    run = json.loads((tmp_path / "r" / "run.json").read_text())
    del run["journal_sha256"]
    (tmp_path / "r" / "run.json").write_text(json.dumps(run))
    calls = []

    class Counting(SyntheticEvaluator):
        def evaluate(self, query):
            calls.append(1)
            return super().evaluate(query)

    run_attack(cfg, tmp_path / "r", show_progress=False, evaluator=Counting)
    assert calls == []  # every query was reused


# ----------------------------------------------------------------------------- real episodes

@pytest.fixture
def scene_path(repo_root):
    p = repo_root / SCENE
    if not p.exists():
        pytest.skip("no bundled scenes")
    return str(p)


def test_restricted_penalised_attack_journals_realism(tmp_path, scene_path, space, ref, monkeypatch):
    """Random search, 3 queries of 1 s with oracle perception, in the Mahalanobis ball with
    class scales: every query's figures respect the region, and the realism weight subtracts
    exactly W x the JSD excess from the objective of the same shapes."""
    from adv3d_runner.attack import evaluator
    from adv3d_runner.attack.report import write_report

    monkeypatch.setattr(evaluator, "_WORKSPACES", {})
    common = dict(algo="random", budget=3, seconds=1.0, autonomy="oracle", seed=2, max_mahalanobis=1.5,
                  class_scales=True)
    run_attack(AttackConfig([scene_path], **common), tmp_path / "plain", show_progress=False)
    s = run_attack(AttackConfig([scene_path], realism_weight=1000.0, **common), tmp_path / "pen", show_progress=False)
    plain, pen = lines(tmp_path / "plain"), lines(tmp_path / "pen")
    assert [r["unit"] for r in plain] == [r["unit"] for r in pen]
    for a, b in zip(plain, pen):
        fig = b["realism"][0]
        assert fig == a["realism"][0]
        assert fig["mahalanobis"] <= 1.5 + 1e-9 and fig["dimension_class"] == "sedan"
        assert fig["dimension_excess"][0] == 0.0 and fig["dimension_excess"][1] == 0.0  # length, width in range
        excess = max(0.0, fig["jsd"] - ref.jsd_limit)
        assert b["components"]["realism_penalty"] == pytest.approx(excess)
        assert "realism_penalty" not in a["components"]
        assert b["cost"] == pytest.approx(a["cost"] - 1000.0 * excess)
    run = json.loads((tmp_path / "pen" / "run.json").read_text())
    assert run["max_mahalanobis"] == 1.5 and run["class_scales"] is True and run["realism_weight"] == 1000.0
    best = s["scenes"]["highway-benchmark-000000"]["modes"]["closed"]["closed_loop_eval"]
    rep = best["realism"][0]
    assert {"genus_robust", "thinnest_wall_m", "limits", "realistic"} <= set(rep) and rep["mahalanobis"] <= 1.5 + 1e-9
    text = write_report([tmp_path / "plain", tmp_path / "pen"], tmp_path / "report.md").read_text()
    assert "random, R 1.5, class scales, W 1000" in text and "## Realism of the best shapes" in text
    table1 = text[text.index("| | scenes |"):].splitlines()
    assert table1[0].endswith("| JSD |") and sum(ln.startswith("| Adv. closed-loop (random") for ln in table1[:6]) == 2


def test_vertex_deformation_attack(tmp_path, scene_path, monkeypatch):
    from adv3d_runner.attack import evaluator

    monkeypatch.setattr(evaluator, "_WORKSPACES", {})
    cfg = AttackConfig([scene_path], algo="random", budget=2, seconds=1.0, autonomy="oracle", shape_model="vd",
                       vd_bound=0.1)
    s = run_attack(cfg, tmp_path / "vd", show_progress=False)
    recs = lines(tmp_path / "vd")
    assert [r["status"] for r in recs] == ["ok", "ok"] and len(recs[0]["unit"][0]) == 162
    assert recs[0]["latent"] is None and recs[0]["realism"][0]["jsd"] > 0
    m = s["scenes"]["highway-benchmark-000000"]["modes"]["closed"]
    rep = m["closed_loop_eval"]["realism"][0]
    assert 0 < rep["max_displacement_m"] <= 0.1 + 1e-12
    assert (tmp_path / "vd" / m["files"]["meshes"]["3"]).exists()
