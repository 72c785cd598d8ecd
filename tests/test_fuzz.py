"""Property-based fuzzing (hypothesis) of every file contract and the CLI's numeric arguments:
each hostile input ends in a one-line error naming the file (and field) or in a documented,
checked acceptance (``tests/fuzz_contracts.py``; figures in docs/reliability.md).

CI runs a fixed-seed subset (derandomized, a few cases per contract); ``-m slow`` runs the full
set (``bench/fuzz.py`` counts the outcomes into ``bench/results/fuzz.json``)."""
from __future__ import annotations

import pytest

pytest.importorskip("hypothesis")

from fuzz_contracts import CONTRACTS, Outcome, fuzz_cli, fuzz_contract, run_case, special_files  # noqa: E402

CI_EXAMPLES = 12
FULL_EXAMPLES = 300


@pytest.mark.parametrize("name", sorted(CONTRACTS))
def test_fuzz_contract_subset(name, tmp_path):
    fuzz_contract(name, tmp_path, CI_EXAMPLES)


def test_fuzz_cli_numbers_subset():
    fuzz_cli(60)


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(CONTRACTS))
def test_fuzz_contract_full(name, tmp_path):
    fuzz_contract(name, tmp_path, FULL_EXAMPLES)


@pytest.mark.slow
def test_fuzz_cli_numbers_full():
    fuzz_cli(2000)


def test_special_files_are_refused_without_reading_them(tmp_path):
    """A device, FIFO, folder, sparse giant, gzip or zip bomb, symlink loop or dangling symlink:
    one error naming the file, at once (nothing is read past the limit)."""
    import time

    from adv3d_runner.scene.schema import load_scene
    from adv3d_runner.validate import read_npz

    for what, path in special_files(tmp_path).items():
        t0 = time.perf_counter()
        load = (lambda p=path: read_npz(p, "points file")) if path.suffix == ".npz" else (lambda p=path: load_scene(p))
        outcome = run_case(load, lambda r: None, path, what)
        assert outcome == Outcome("error", what, outcome.message), (what, outcome)
        assert time.perf_counter() - t0 < 5.0, what
