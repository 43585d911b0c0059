"""``prml2 train``: train a PRML2 model (NLL pretraining, then fine-tuning through the differentiable EKF).

Examples::

    prml2 train --data data/bench --out runs/edge --preset edge            # PRML2 (the shipped recipe)
    prml2 train --data data/bench --out runs/edge_star --preset edge --no-finetune   # PRML2*
    prml2 train --data data/bench --out runs/edge --preset edge --resume runs/edge/last.pt
    prml2 train --data data/bench --out runs/nn-vdm --model nn-vdm   # a learned baseline (also dl-avl,
                                                                      # rnn-ekf, backprop-kf)
    torchrun --nproc_per_node 2 -m prml2_edge.cli.main train --data data/bench --out runs/ddp --preset edge

Writes ``RUN/best.pt`` (export this), ``RUN/last.pt`` (resume from this), ``RUN/metrics.jsonl``,
``RUN/loss_curve.png`` and ``RUN/summary.json`` (final validation: z RMSE of the model and of the
OSD baseline, 60 s dead reckoning, guard fire rate, wall time).
"""

from __future__ import annotations

import argparse
import json
import math
import time
from dataclasses import asdict
from pathlib import Path

HELP = "Train a PRML2 model (NLL pretraining, then fine-tuning through the differentiable EKF)."
NEEDS: tuple[tuple[str, str], ...] = (("torch", "train"),)

PRESET_NAMES = ("paper", "edge", "tiny")  # kept here so --help works without importing torch
MODEL_NAMES = ("prml2", "nn-vdm", "dl-avl", "rnn-ekf", "backprop-kf")  # baselines: prml2_edge.training.baselines


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--data", required=True, metavar="DIR",
                        help="dataset folder (prml2 simulate, or ReV-StED CSVs)")
    parser.add_argument("--out", required=True, metavar="RUN", help="run folder for checkpoints, metrics and plots")
    parser.add_argument("--preset", default="edge", choices=PRESET_NAMES,
                        help="model size and training defaults (default: edge, the shipped one)")
    parser.add_argument("--model", default="prml2", choices=MODEL_NAMES,
                        help="what to train: prml2 (default) or a learned baseline of the paper's Table 1-2")
    parser.add_argument("--hidden", type=int, default=48, help="baselines: hidden size (default 48)")
    parser.add_argument("--no-finetune", action="store_true",
                        help="PRML2*: NLL pretraining for all epochs, no fine-tuning through the EKF")
    parser.add_argument("--nll-reduction", choices=("sum", "mean"),
                        help="NLL over a window's decoder steps: 'sum' (the paper's) or 'mean' (the position term "
                             "of fine-tuning then weighs in); default: the preset's")
    parser.add_argument("--ft-horizon", type=float, metavar="SECONDS",
                        help="fine-tune through the EKF across consecutive windows over segments this long "
                             "(0: the paper's, each window's 2 s of decoder steps); default: the preset's")
    parser.add_argument("--epochs", type=int, help="total epochs (70%% pretraining, 30%% fine-tuning)")
    parser.add_argument("--batch-size", type=int, help="windows per optimizer step, over all processes")
    parser.add_argument("--lr", type=float, help="Adam learning rate at the start of each stage")
    parser.add_argument("--window-stride", type=int, help="samples between training windows")
    parser.add_argument("--seed", type=int, help="random seed (weights and shuffling)")
    parser.add_argument("--threads", type=int, help="torch CPU threads per process (default 2)")
    parser.add_argument("--max-train-windows", type=int, help="use at most this many training windows per epoch")
    parser.add_argument("--pretrain-physics", type=float, metavar="LAMBDA",
                        help="add LAMBDA x (acceleration consistency + jerk) to the pretraining NLL, as the "
                             "authors' public code does with 0.5 (default 0: the paper's loss)")
    parser.add_argument("--yaw-offset-aug", type=float, metavar="DPS",
                        help="add a random CAN yaw-rate offset within +-DPS deg/s to each training window's input "
                             "(the target stays the truth), so that the model does not pass a gyro offset through "
                             "(default 0: off)")
    parser.add_argument("--yaw-quant-aug", type=float, metavar="SHARE",
                        help="round the input yaw rate of this share (0-1) of the training windows to a coarse "
                             "gyro's step (0.2-1.5 deg/s), so that the model learns to read the rate within a step "
                             "from the other signals (default 0: off)")
    parser.add_argument("--omega-residual", action="store_true",
                        help="residual form: the model's omega_z is the CAN yaw rate plus a learned correction "
                             "(zero transformer part at the start) instead of a direct output (default: off)")
    parser.add_argument("--cue-debiased-inputs", action="store_true",
                        help="the model reads a_y and steering less the car's offsets: trained on the simulated "
                             "drives' own, fed the cue estimator's on the car (simulated data only; default: off)")
    parser.add_argument("--pretrain-frac", type=float, metavar="F",
                        help="share of the epochs spent pretraining (default 0.7, the paper; the authors' code 0.8)")
    parser.add_argument("--beta", type=float, help="fine-tuning position-loss scale (default 8, the paper; "
                                                   "the authors' code 10)")
    parser.add_argument("--resume", metavar="CKPT", help="continue a run from its last.pt (same options)")
    parser.add_argument("--init", metavar="MODEL",
                        help="transfer to a new car: start from this trained model (a best.pt checkpoint or a "
                             "'prml2 export' .onnx, e.g. the shipped one) with its config and input statistics, "
                             "and train it on --data (a few minutes of the new car's drives with reference data)")
    parser.add_argument("--vehicle", metavar="NAME",
                        help="train on this vehicle's drives of --data only (its own train/val splits, also a "
                             "held-out car's; e.g. --vehicle suv_awd on the benchmark)")
    parser.add_argument("--eval-stride", type=int, default=1,
                        help="streaming stride [samples] of the final validation (default 1)")
    parser.add_argument("--no-eval", action="store_true",
                        help="skip the final validation (z RMSE, 60 s dead reckoning)")


def _model_config(args: argparse.Namespace, preset_model, init):
    """The model's config: ``--init``'s, else the preset's, with ``--omega-residual`` and
    ``--cue-debiased-inputs`` applied."""
    from prml2_edge.training.presets import with_overrides

    cfg = init.cfg if init is not None else preset_model
    changes = {k: True for k, on in (("omega_residual", args.omega_residual),
                                     ("cue_debiased_inputs", args.cue_debiased_inputs)) if on and not getattr(cfg, k)}
    if not changes:
        return cfg
    if init is not None:
        from prml2_edge.errors import ConfigError

        flag = "--" + next(iter(changes)).replace("_", "-")
        raise ConfigError(f"{flag} changes what the model computes or reads, and --init's model was trained without "
                          "it: train from scratch, or leave the flag out")
    return with_overrides(cfg, changes)


def _run_baseline(args: argparse.Namespace) -> int:
    """``--model NAME`` for a learned baseline: same data, windows and statistics as PRML2's trainer."""
    from dataclasses import replace

    from prml2_edge.data.datasets import load_dataset
    from prml2_edge.training.baselines.models import BaselineConfig
    from prml2_edge.training.baselines.train import BaselineTrainConfig, fit_baseline
    from prml2_edge.training.presets import get_preset, with_overrides
    from prml2_edge.training.trainer import prepare_data

    t0 = time.monotonic()
    if args.resume or args.no_finetune or args.init or args.omega_residual or args.cue_debiased_inputs:
        from prml2_edge.errors import ConfigError

        raise ConfigError("--resume, --init, --no-finetune, --omega-residual and --cue-debiased-inputs apply to "
                          "--model prml2 only")
    preset = get_preset(args.preset)
    train_cfg = with_overrides(preset.train, {"window_stride": args.window_stride})
    tcfg = BaselineTrainConfig(epochs=6, max_train_windows=4096, lr=2e-3, num_threads=1)
    tcfg = replace(tcfg, **{k: v for k, v in {"epochs": args.epochs, "batch_size": args.batch_size, "lr": args.lr,
                                              "seed": args.seed, "num_threads": args.threads,
                                              "max_train_windows": args.max_train_windows}.items() if v is not None})
    cfg = BaselineConfig(kind=args.model, hidden=args.hidden)
    dataset = load_dataset(args.data)
    if args.vehicle:
        dataset = dataset.for_vehicle(args.vehicle)
    data = prepare_data(dataset, preset.model, train_cfg)
    print(f"prml2 train: baseline {args.model} (hidden {args.hidden}), {tcfg.epochs} epochs of at most "
          f"{tcfg.max_train_windows or len(data.train)} of {len(data.train)} training windows, dataset "
          f"{dataset.fingerprint[:12]}")
    best = fit_baseline(data, args.out, cfg, tcfg)
    summary = {"model": args.model, "data": str(args.data), "dataset_fingerprint": dataset.fingerprint,
               "model_config": asdict(cfg), "train_config": asdict(tcfg), "total_wall_s": time.monotonic() - t0}
    Path(args.out, "summary.json").write_text(json.dumps(summary, indent=1, sort_keys=True, default=str))
    print(f"done in {summary['total_wall_s'] / 60:.1f} min: {best} (export it with 'prml2 export --checkpoint')")
    return 0


def _initial_model(path: str):
    """The model ``--init`` names: a training checkpoint or an exported .onnx (weights read back from the graph)."""
    if str(path).endswith(".onnx"):
        from prml2_edge.training.export_onnx import model_from_onnx

        return model_from_onnx(path)[0]
    from prml2_edge.training.checkpoint import load_model

    return load_model(path)[0]


def run(args: argparse.Namespace) -> int:
    if getattr(args, "model", "prml2") != "prml2":
        return _run_baseline(args)
    import torch

    from prml2_edge.data.datasets import load_dataset
    from prml2_edge.training import distributed as ddp
    from prml2_edge.training.presets import get_preset, with_overrides
    from prml2_edge.training.trainer import fit, prepare_data

    t0 = time.monotonic()
    preset = get_preset(args.preset)
    if args.init and args.resume:
        from prml2_edge.errors import ConfigError

        raise ConfigError("--init starts a new run from a trained model; --resume continues one: give one of them")
    train_cfg = with_overrides(preset.train, {
        "epochs": args.epochs, "batch_size": args.batch_size, "lr": args.lr, "window_stride": args.window_stride,
        "seed": args.seed, "num_threads": args.threads, "max_train_windows": args.max_train_windows,
        "finetune": False if args.no_finetune else None, "nll_reduction": args.nll_reduction,
        "ft_horizon_s": args.ft_horizon, "pretrain_physics": args.pretrain_physics,
        "pretrain_frac": args.pretrain_frac, "beta": args.beta, "yaw_offset_aug_dps": args.yaw_offset_aug,
        "yaw_quant_aug": args.yaw_quant_aug,
    })
    train_cfg.validate()
    torch.set_num_threads(train_cfg.num_threads)
    info = ddp.init()
    try:
        dataset = load_dataset(args.data)
        if args.vehicle:
            dataset = dataset.for_vehicle(args.vehicle)
        init = _initial_model(args.init) if args.init else None
        model_cfg = _model_config(args, preset.model, init)
        data = prepare_data(dataset, model_cfg, train_cfg)
        if info.is_main:
            stages = (f"{train_cfg.pretrain_epochs()} pretraining + {train_cfg.epochs - train_cfg.pretrain_epochs()} "
                      "fine-tuning" if train_cfg.finetune else f"{train_cfg.epochs} pretraining (PRML2*)")
            print(f"prml2 train: preset {preset.name}, {stages} epochs, {len(data.train)} training / "
                  f"{len(data.val)} validation windows, {info.world_size} process(es), "
                  f"dataset {dataset.fingerprint[:12]}")

        result = fit(data, args.out, preset=preset.name, model_cfg=model_cfg, train_cfg=train_cfg,
                     resume=args.resume, info=info, on_epoch=_print_epoch, init=init)
        summary: dict = {
            "preset": preset.name, "data": str(args.data), "dataset_fingerprint": dataset.fingerprint,
            "train_config": asdict(train_cfg), "model_config": asdict(model_cfg), "init": args.init,
            "vehicle": args.vehicle,
            "world_size": info.world_size, "train_wall_s": result.wall_s, "counters": result.counters,
        }
        if info.is_main and not args.no_eval:
            summary["val"] = _final_validation(result.best_path, dataset, args.eval_stride)
        summary["total_wall_s"] = time.monotonic() - t0
        summary["kept_initial_model"] = kept = init is not None and _kept_initial(result.history)
        if info.is_main and kept:
            print("no epoch of the last stage beat the initial model on the validation windows: best.pt is the "
                  "model it started from (--init)")
        if info.is_main:
            Path(args.out, "summary.json").write_text(json.dumps(summary, indent=1, sort_keys=True, default=str))
            print(f"done in {summary['total_wall_s'] / 60:.1f} min: {result.best_path} (best), "
                  f"{result.metrics_path}, {Path(args.out, 'loss_curve.png')}; skipped steps: "
                  f"{result.counters.get('skipped_nonfinite', 0)} non-finite, "
                  f"{result.counters.get('skipped_exploding', 0)} exploding")
    finally:
        ddp.shutdown(info)
    return 0


def _print_epoch(r: dict) -> None:
    """One line per epoch (``fit``'s ``on_epoch``); a transfer's epoch 0 is its initial model, validated."""
    finite = math.isfinite(r["val_pos"])
    pos = f" pos {r['val_pos']:.3f}" if r["stage"] in ("finetune", "initial") and finite else ""
    best = " *best" if r["best"] else ""
    if r["stage"] == "initial":  # a transfer's starting model on the new car's validation windows
        print(f"epoch   0 initial  (--init) | val nll {r['val_nll']:.2f}{pos} | v_x {r['val_rmse_v_x_mps']:.3f} "
              f"m/s, w_z {r['val_rmse_omega_z_radps']:.4f} rad/s{best}")
        return
    print(f"epoch {r['epoch']:>3} {r['stage']:<8} train {r['train_loss']:.2f} | val nll {r['val_nll']:.2f}"
          f"{pos} | v_x {r['val_rmse_v_x_mps']:.3f} m/s, w_z {r['val_rmse_omega_z_radps']:.4f} rad/s"
          f" | {r['train_windows_per_s']:.0f} win/s, {r['epoch_time_s']:.0f} s{best}")


def _kept_initial(history: list[dict]) -> bool:
    """A transfer run in which no epoch of its last stage beat the initial model (best.pt is that model)."""
    last = history[-1]["stage"] if history else None
    return not any(r["best"] for r in history if r["stage"] == last)


def _final_validation(best_path, dataset, eval_stride: int) -> dict:
    """Stream ``best_path`` over the validation split, print z RMSE and 60 s dead reckoning; the metrics."""
    from prml2_edge.training.checkpoint import load_model
    from prml2_edge.training.validate import evaluate_split

    model, _ = load_model(best_path)
    print(f"final validation of {best_path} (streaming stride {eval_stride}) ...")
    val = evaluate_split(model, dataset, "val", stride=eval_stride)
    dr = val.dr_summary()
    print("val z RMSE   " + "  ".join(f"{k} {v:.4f}" for k, v in val.z_rmse.items()))
    print("OSD baseline " + "  ".join(f"{k} {v:.4f}" for k, v in val.osd_z_rmse.items()))
    if dr.get("n_windows"):
        print(f"val 60 s dead reckoning over {dr['n_windows']} windows: position RMSE "
              f"{dr['rmse_mean_m']:.2f} ± {dr['rmse_std_m']:.2f} m, ME {dr['me_mean_m']:.2f} ± "
              f"{dr['me_std_m']:.2f} m; guard fired on {100 * val.guard_fire_rate:.2f} % of predictions")
    return val.to_dict()
