"""Every recipe ``prml2 simulate --help`` offers goes through ``train``, ``export`` and ``evaluate``.

``small`` runs as shipped, with the protocol's 60 s windows; ``benchmark`` (3.8 h) keeps its structure
here (a drive per split, the snow drives, the held-out car) with one fleet car and the held-out one, each
drive cut to one 20 s window (the full recipe's 60 s window counts: tests/data/test_data_datasets.py).
A tiny model, a few training steps.
"""

from __future__ import annotations

import json

import pytest

from prml2_edge.cli.main import main
from prml2_edge.cli.simulate import add_arguments
from prml2_edge.data.datasets import FLEET, HELDOUT, RECIPES, generate_dataset, resolve_recipe
from prml2_edge.training.export_onnx import read_metadata

pytest.importorskip("torch")


def offered_recipes() -> list[str]:
    """The recipe names the ``--recipe`` help of ``prml2 simulate`` names."""
    import argparse

    parser = argparse.ArgumentParser()
    add_arguments(parser)
    help_text = next(a.help for a in parser._actions if a.dest == "recipe")
    return [name for name in RECIPES if f"'{name}'" in help_text]


def benchmark_in_brief() -> dict:
    """The benchmark's first fleet car and its held-out car, their drives cut to one 20 s window each."""
    recipe = resolve_recipe("benchmark")
    keep = (FLEET[0], *HELDOUT)
    drives = [{**d, "minutes": 0.5 if d["split"] == "train" else 0.45} for d in recipe["drives"]
              if d["vehicle"] in keep]
    return {**recipe, "name": "benchmark-brief", "drives": drives}


def test_simulate_offers_every_recipe():
    assert offered_recipes() == list(RECIPES) == ["benchmark", "small"]


# small: the user's path as it is (60 s windows, the deployment protocol's pre-roll, OSD tuned on val); benchmark in
# brief: 20 s windows, no pre-roll, the model named PRML2 (the ablation of Table 3 runs too) and the held-out car
SETTINGS = {
    "small": (["--models", "OSD-Baseline=osd", "tiny={onnx}"], "tiny"),
    "benchmark": (["--models", "OSD-Baseline=osd", "PRML2={onnx}", "--window-s", "20", "--preroll-s", "0"], "PRML2"),
}


@pytest.mark.slow
@pytest.mark.parametrize("recipe", offered_recipes())
def test_recipe_through_train_export_and_evaluate(recipe, tmp_path, capsys):
    data = tmp_path / "data"
    if recipe == "small":
        assert main(["simulate", "--recipe", "small", "--out", str(data), "--workers", "1"]) == 0
    else:
        generate_dataset(data, benchmark_in_brief(), workers=1, progress=False)
    run = tmp_path / "run"
    final_validation = [] if recipe == "small" else ["--no-eval"]  # small: train's own 60 s val check too
    assert main(["train", "--data", str(data), "--out", str(run), "--preset", "tiny", "--epochs", "2",
                 "--max-train-windows", "8", *final_validation]) == 0
    if recipe == "small":
        assert json.loads((run / "summary.json").read_text())["val"]["dead_reckoning_60s"]["n_windows"] == 1
    onnx = tmp_path / "m.onnx"
    assert main(["export", "--checkpoint", str(run / "best.pt"), "--out", str(onnx), "--data", str(data)]) == 0
    # the model's slow error measured on the 60 s validation window (small), or said not measured (brief: none)
    error_model = read_metadata(onnx).error_model
    assert (error_model is not None) == (recipe == "small")
    if error_model is not None:
        assert len(error_model["var_inflation"]) == 5 and min(error_model["var_inflation"]) >= 1.0
    else:
        assert "error model: not measured" in capsys.readouterr().out
    # a transfer from the exported model: its epoch 0 is the model itself, validated, and the summary says whether
    # an epoch beat it
    assert main(["train", "--data", str(data), "--out", str(tmp_path / "ft"), "--init", str(onnx), "--epochs", "2",
                 "--max-train-windows", "8", "--no-eval"]) == 0
    assert "epoch   0 initial  (--init) | val nll" in capsys.readouterr().out
    assert isinstance(json.loads((tmp_path / "ft" / "summary.json").read_text())["kept_initial_model"], bool)
    rep = tmp_path / "rep"
    args, model = SETTINGS[recipe]
    assert main(["evaluate", "--data", str(data), *(a.format(onnx=onnx) for a in args), "--out", str(rep),
                 "--max-windows", "1", "--calibration", "off", "--no-plots", "--no-tum"]) == 0
    metrics = json.loads((rep / "metrics.json").read_text())
    parts = {"small": ("test", "snow", "deployment"), "benchmark": ("test", "snow", "heldout")}[recipe]
    for name in ("OSD-Baseline", model):
        for part in parts:
            assert metrics["models"][name][part]["dead_reckoning_60s"]["n_windows"] >= 1, (name, part)
    assert "OSD-Baseline" in metrics["tuning"]
    assert ("ablation" in metrics) == (recipe == "benchmark")
    assert "report:" in capsys.readouterr().out


def test_evaluate_without_validation_windows_says_how_to_get_them(tmp_path, capsys):
    """A dataset whose drives are split 70:10:20 and too short for a 60 s validation window: the OSD baseline
    cannot be tuned, and the one line says how long the segments are and what to do."""
    data = generate_dataset(tmp_path / "short", {"name": "short", "drives": [
        {"name": "d0", "family": "mixed", "mu": 1.0, "seed": 1, "minutes": 2.0}]}, workers=1, progress=False)
    assert main(["evaluate", "--data", str(data), "--models", "osd", "--out", str(tmp_path / "rep")]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err and "--debug" not in err, err
    assert "no 60 s val windows to tune the OSD baseline's noise" in err and "longest segment" in err
    assert "12.0 s" in err and '"split": "val"' in err and "--window-s" in err
