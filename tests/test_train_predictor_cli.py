"""``adv3d train predictor`` (docs/predictor.md, "Training"): it trains the shipped kind (the
anchored model) by default with the options and defaults of ``predictor_anchored.train_anchored``,
the older free model only with ``--model free``, and never writes over a model without --force.
These run the command line up to its refusals, before any data is made (seconds); the training
itself is in the slow tests of test_predictor_anchored.py and test_predictor.py."""
from __future__ import annotations

import inspect
from pathlib import Path

import pytest

from adv3d_runner.autonomy.names import MODEL_DIRS
from adv3d_runner.cli import build_parser, main


def _run(capsys, *argv) -> tuple[int, str]:
    try:
        rc = main(["-q", "train", "predictor", *map(str, argv)])
    except SystemExit as exc:
        rc = exc.code
    return rc, capsys.readouterr().err


def _model(folder: Path) -> Path:
    folder.mkdir(parents=True)
    (folder / "config.json").write_text("{}")
    return folder


def test_default_is_the_anchored_model_with_the_trainers_defaults():
    """The parser's defaults (resolved for --model anchored) are train_anchored's keyword defaults,
    and --out defaults to the shipped model's folder."""
    pytest.importorskip("torch")
    from adv3d_runner.training.cli import ANCHORED_DEFAULTS
    from adv3d_runner.training.predictor_anchored import train_anchored

    args = build_parser().parse_args(["train", "predictor"])
    assert args.model == "anchored" and Path(args.out) == MODEL_DIRS["predictor"] and not args.force
    sig = inspect.signature(train_anchored).parameters
    assert {k: sig[k].default for k in ANCHORED_DEFAULTS} == ANCHORED_DEFAULTS
    assert args.seed == sig["seed"].default


def test_help_names_the_model_kinds_and_force(capsys):
    with pytest.raises(SystemExit):
        main(["train", "predictor", "--help"])
    out = capsys.readouterr().out
    assert "--model {anchored,free}" in out and "--force" in out and "scenes/real/split.json" in out


def test_an_existing_model_is_refused_without_force(tmp_path, capsys):
    """A folder with a model at --out: one usage line naming it and --force, exit 2, nothing made
    (no data cache); the same through ``python -m adv3d_runner.training.predictor_anchored``."""
    from adv3d_runner.training.predictor_anchored import main as anchored_main

    out = _model(tmp_path / "m")
    for argv in ([], ["--model", "free"]):
        rc, err = _run(capsys, "--out", out, "--cache", tmp_path / "cache", *argv)
        assert rc == 2 and f"--out {out}: a model is already there" in err and "--force" in err, err
    assert anchored_main(["--out", str(out), "--cache", str(tmp_path / "cache")]) == 2
    assert "a model is already there" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m"] and [p.name for p in out.iterdir()] == ["config.json"]


@pytest.mark.skipif(not (MODEL_DIRS["predictor"] / "weights.pt").is_file(), reason="no shipped predictor")
def test_the_shipped_model_is_not_overwritten_by_default(capsys):
    before = (MODEL_DIRS["predictor"] / "weights.pt").stat().st_mtime_ns
    rc, err = _run(capsys)
    assert rc == 2 and str(MODEL_DIRS["predictor"]) in err and "--force" in err, err
    assert (MODEL_DIRS["predictor"] / "weights.pt").stat().st_mtime_ns == before


@pytest.mark.parametrize("argv, option", [
    (["--model", "free", "--gen-scenes", "3"], "--gen-scenes applies to --model anchored"),
    (["--model", "free", "--val-recording", "5"], "--val-recording applies to --model anchored"),
    (["--scenes", "3"], "--scenes applies to --model free"),
    (["--quick"], "--quick applies to --model free"),
    (["--device", "auto"], "--device auto"),
    (["--seed", "1"], "--seed 1 --gen-scenes 160"),
])
def test_options_of_the_other_model_kind_are_usage_errors(tmp_path, capsys, argv, option):
    rc, err = _run(capsys, "--out", tmp_path / "new", *argv)
    assert rc == 2 and option in err, err
    assert not (tmp_path / "new").exists()


def test_a_missing_split_manifest_names_its_folder(tmp_path, capsys):
    missing = tmp_path / "recordings" / "split.json"
    rc, err = _run(capsys, "--out", tmp_path / "new", "--real", missing)
    assert rc == 2 and f"--real {missing}" in err and str(missing.parent) in err, err
    assert not (tmp_path / "new").exists()
