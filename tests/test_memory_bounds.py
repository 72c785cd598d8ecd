"""Every input that sets a size is bounded before anything is allocated (docs/reliability.md,
"Memory"): the vertex-deformation lattice and the search budget (the searcher's arrays), a
scene's dt (an episode's frames), its actor count and actors x frames, its size in bytes. Each
is refused with one error naming the option or field, in well under a second, without
allocating what it asks for."""
from __future__ import annotations

import gzip
import json
import time
import tracemalloc
from pathlib import Path

import numpy as np
import pytest

from adv3d_runner.attack.config import AttackConfig
from adv3d_runner.attack.driver import run_attack
from adv3d_runner.attack.search import (_BO_CANDIDATES, check_search_memory, make_searcher, matern32_product,
                                        search_memory)
from adv3d_runner.errors import ConfigError, FileFormatError
from adv3d_runner.fileio import MEMORY_BUDGET
from adv3d_runner.scene import schema

REPO = Path(__file__).resolve().parent.parent
SCENE = REPO / "scenes" / "highway" / "highway-benchmark-000000.json.gz"


def _scene_doc() -> dict:
    return json.loads(gzip.decompress(SCENE.read_bytes()))


def _refused_quickly(fn, exc_type, match: str, seconds: float = 10.0, peak_mib: float = 64.0):
    """``fn`` raises ``exc_type`` matching ``match`` within ``seconds`` (generous: tracemalloc
    slows allocation, and the machine may be shared; each takes well under a second idle),
    having allocated at most ``peak_mib`` MiB (Python's allocations, numpy's included)."""
    tracemalloc.start()
    t0 = time.perf_counter()
    try:
        with pytest.raises(exc_type, match=match) as info:
            fn()
    finally:
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    assert time.perf_counter() - t0 < seconds
    assert peak < peak_mib * 2**20, f"{peak / 2**20:.0f} MiB allocated before the refusal"
    assert "\n" not in str(info.value)
    return info.value


# ------------------------------------------------------------------ search: lattice, budget

def test_a_huge_vertex_deformation_lattice_is_refused_naming_the_option():
    """--shape-model vd --vd-lattice 1000,1000,1000 asked for 246 GiB (the Latin hypercube of
    3e9 dimensions); now the config refuses it, naming --vd-lattice, before any array exists."""
    exc = _refused_quickly(lambda: AttackConfig(["s.json"], shape_model="vd", vd_lattice=(1000, 1000, 1000)),
                           ConfigError, r"^--vd-lattice 1000,1000,1000 .*GiB of memory, more than the 4 GiB budget")
    assert "3000000000 dimensions per actor" in str(exc)
    # a hand-edited run.json: the field is named
    run = {**AttackConfig(["s.json"], shape_model="vd").run_json(), "vd_lattice": [1000, 1000, 1000]}
    with pytest.raises(FileFormatError, match=r"run\.json: \$\.vd_lattice: .*--vd-lattice 1000,1000,1000"):
        AttackConfig.from_run_json(run, "run.json")
    # the paper's lattices fit: the default 6 x 3 x 3 and a fine 20 x 10 x 10 (6000 dimensions)
    AttackConfig(["s.json"], shape_model="vd")
    AttackConfig(["s.json"], shape_model="vd", vd_lattice=(20, 10, 10))


def test_the_attack_command_refuses_the_lattice_before_writing(tmp_path, capsys):
    from adv3d_runner.cli import main

    code = main(["attack", str(SCENE), "--shape-model", "vd", "--vd-lattice", "1000,1000,1000", "--out",
                 str(tmp_path / "run")])
    assert code in (1, 2)
    err = capsys.readouterr().err
    assert "--vd-lattice" in err and "GiB" in err and err.count("\n") == 1
    assert not (tmp_path / "run").exists()


def test_a_search_budget_beyond_memory_is_refused():
    """BO's GP holds budget^2 covariances: a budget whose matrices pass 4 GiB is refused, naming
    --budget; so is a grid of 3^D points over too many actors, naming --actors."""
    with pytest.raises(ConfigError, match=r"^--budget 20000: --algo bo .*GiB"):
        AttackConfig(["s.json"], budget=20000)
    AttackConfig(["s.json"], budget=20000, algo="random")   # random search keeps only its history
    with pytest.raises(ConfigError, match=r"^--actors 64: --algo grid"):
        AttackConfig(["s.json"], algo="grid", actors=64)
    # the protocol's searches are far inside: BO 100 queries on 5 actors, Table 5's random search
    # on 5 x 100, Table 3's default lattice
    for algo, dim, budget in (("bo", 25, 100), ("skopt", 5, 100), ("random", 5, 500), ("grid", 5, 243),
                              ("blendsearch", 5, 100), ("bo", 162, 100)):
        assert search_memory(algo, dim, budget) < MEMORY_BUDGET / 16, (algo, dim, budget)


def test_the_run_checks_the_searchs_exact_size_before_writing(tmp_path):
    """The latent model's dimension comes from the shape space (K + 2 per actor): run_attack
    checks the exact search size per scene before the run folder is made."""
    from attack_synthetic import SyntheticEvaluator

    class Wide(SyntheticEvaluator):
        def targets(self, ref):
            return [0], 10**9

    cfg = AttackConfig(["synthetic:peak"], algo="random", budget=4)
    _refused_quickly(lambda: run_attack(cfg, tmp_path / "run", evaluator=Wide, show_progress=False), ConfigError,
                     r"^synthetic:peak: --actors 1 \(1 attacked, 1000000000 dimensions each\): --algo random")
    assert not (tmp_path / "run").exists()


def test_search_memory_is_an_upper_bound_of_what_bo_allocates():
    """search_memory's estimate of BO is above what BO's last ask allocates (measured)."""
    dim, budget = 40, 60
    bo = make_searcher("bo", dim, seed=0, budget=budget, n_initial=budget - 1)  # a Latin hypercube first
    X = bo.ask(budget - 1)
    bo.tell(X, np.random.default_rng(0).random(len(X)))
    tracemalloc.start()
    bo.ask(1)   # the GP over 59 points, 2648 candidates scored
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert peak < search_memory("bo", dim, budget, budget - 1)
    check_search_memory("bo", dim, budget, budget - 1)


def test_the_kernel_in_blocks_is_the_kernel():
    """matern32_product computes rows in blocks past 32 MiB of temporaries: the same bits."""
    from adv3d_runner.attack import search

    rng = np.random.default_rng(1)
    A, B = rng.random((_BO_CANDIDATES, 7)), rng.random((90, 7))
    whole = search._matern32_block(A, B, 0.1)
    saved = search._KERNEL_BLOCK_BYTES
    try:
        search._KERNEL_BLOCK_BYTES = 8 * 90 * 7 * 13   # 13 rows a block
        blocks = matern32_product(A, B, 0.1)
    finally:
        search._KERNEL_BLOCK_BYTES = saved
    assert np.array_equal(whole, blocks)


# ------------------------------------------------------------------ scenes: dt, actors, bytes

def test_a_scene_with_a_nanosecond_dt_is_refused_at_validation(tmp_path):
    """dt = 1e-9 passed validation and a 5 s episode asked for 5e9 frames (67 GiB); dt is now at
    least 1 ms, and an episode at most MAX_FRAMES frames whatever dt and --seconds are."""
    doc = _scene_doc()
    doc["dt"] = 1e-9
    path = tmp_path / "dt.json"
    path.write_text(json.dumps(doc))
    _refused_quickly(lambda: schema.load_scene(path), FileFormatError, r"dt\.json: \$\.dt: expected a number >= 0\.001")
    from adv3d_runner.sim.episode import _episode_frames

    doc["dt"] = schema.MIN_DT
    path.write_text(json.dumps(doc))
    scene = schema.load_scene(path)
    with pytest.raises(ConfigError, match=r"--seconds 3600 at the scene's dt of 0\.001 s is 3600000 frames"):
        _episode_frames(scene, 3600.0, True, 0)


def _many_actors_gz(n: int, frames: int | None = None) -> bytes:
    """A scene file (gzip) with ``n`` one-frame actors (the scene's own frames unless given),
    built as bytes (fast: the actors are the same text; the count is checked before their ids
    are read)."""
    doc = _scene_doc()
    doc["actors"] = []
    if frames is not None:
        doc["frames"] = frames
    head = json.dumps(doc, separators=(",", ":")).encode()
    actor = b'{"id":1,"class":"car","dimensions":[4.5,1.8,1.5],"track":{"start":0,"x":[0.0],"y":[0.0],"yaw":[0.0]}}'
    body = head.replace(b'"actors":[]', b'"actors":[' + b",".join([actor] * n) + b"]")
    return gzip.compress(body, 1)


def test_a_million_one_frame_actors_are_refused_in_seconds(tmp_path):
    """10^6 one-frame actors (6 MiB gzipped) took 189 s and 3.2 GB to validate: the scene is over
    its 64 MiB size now, refused while it is inflated."""
    path = tmp_path / "many.json.gz"
    path.write_bytes(_many_actors_gz(10**6))
    _refused_quickly(lambda: schema.load_scene(path), FileFormatError, r"many\.json\.gz: \$: expected at most 64 MiB",
                     seconds=15.0, peak_mib=400)


def test_the_actor_count_is_checked_before_any_actor_is_read(tmp_path):
    """Under the size limit: more than MAX_ACTORS actors, or actors x frames past the memory
    budget, refused on the list's length (no actor validated, so linear and short)."""
    path = tmp_path / "s.json.gz"
    path.write_bytes(_many_actors_gz(schema.MAX_ACTORS + 1))   # 1 MB of JSON
    _refused_quickly(lambda: schema.load_scene(path), FileFormatError,
                     r"\$\.actors: expected at most 10000 actors \(got '10001 actors'\)", peak_mib=128)
    path.write_bytes(_many_actors_gz(1000, frames=schema.MAX_FRAMES))
    _refused_quickly(lambda: schema.load_scene(path), FileFormatError,
                     r"\$\.actors: expected at most 671 actors for 100000 frames .* memory budget")
    path.write_bytes(_many_actors_gz(schema.MAX_ACTORS))   # at the bound: the actors are read (an id repeats)
    t0 = time.perf_counter()
    with pytest.raises(FileFormatError, match=r"\$\.actors\[1\]\.id: .*unique"):
        schema.load_scene(path)
    assert time.perf_counter() - t0 < 15.0


def test_a_scene_too_big_to_read_back_is_never_written(tmp_path, monkeypatch):
    scene = schema.load_scene(SCENE)
    monkeypatch.setattr(schema, "MAX_SCENE_BYTES", 10_000)
    with pytest.raises(FileFormatError, match=r"x\.json: \$: expected a scene of at most"):
        schema.save_scene(scene, tmp_path / "x.json")
    assert not (tmp_path / "x.json").exists()


def test_json_depth_is_measured_in_blocks():
    """fileio._depth walks the text in blocks (its temporaries were 9 bytes per byte of JSON):
    the same depth as one pass, across block boundaries."""
    from adv3d_runner import fileio

    rng = np.random.default_rng(2)
    text = bytes(rng.choice(np.frombuffer(b"[]{}x", np.uint8), 3 * fileio._DEPTH_BLOCK + 11))
    codes = np.frombuffer(text, np.uint8)
    steps = np.frombuffer(fileio._BRACKETS, np.int8)[codes]  # +1 opens, -1 closes, 0 else
    assert fileio._depth(text) == int(np.cumsum(steps, dtype=np.int64).max())
    deep = b"[" * 70 + b"]" * 70
    saved = fileio._DEPTH_BLOCK
    try:
        fileio._DEPTH_BLOCK = 16
        assert fileio._depth(deep) == 70 and fileio._depth(b"") == 0
    finally:
        fileio._DEPTH_BLOCK = saved
