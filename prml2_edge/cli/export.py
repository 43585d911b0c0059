"""``prml2 export``: export a trained checkpoint to ONNX for the edge runtime.

Examples::

    prml2 export --checkpoint runs/edge/best.pt --out export/default/prml2_edge.onnx
    prml2 export --checkpoint runs/edge/best.pt --out out/prml2_edge_int8.onnx --int8 --data data/bench
    prml2 export --checkpoint runs/edge/best.pt --out out/prml2_edge_s8.onnx --int8 static --data data/bench
    prml2 export --checkpoint runs/edge/best.pt --out out/prml2_edge_opt.onnx --optimize
    prml2 export --checkpoint old_all_rows.onnx --out prml2_stream.onnx     # re-export an exported model

The graph has a fixed input ``onboard`` float32 (1, L, 9) in raw SI units and outputs ``z_mean``,
``z_var`` (1, R, 5) before the physics guard (which runs in NumPy at runtime) for the newest
R = ``--rows`` decoder steps: 1 by default, the one the streaming runtime consumes (the last decoder
layer then computes a single query row), ``--rows all`` for every one of the L - H; the metadata
(``prml2_edge.model_meta``) is embedded. Every export is checked against torch on at least 100
windows (max abs difference <= 1e-4). ``--int8`` (or ``--int8 dynamic``) applies onnxruntime dynamic
quantisation, ``--int8 static`` static QDQ quantisation calibrated on windows of simulated drives
(the project's simulator, ``--calibration-windows``; never the dataset); both print the z RMSE of
the fp32 and int8 graphs on validation windows (needs ``--data``). ``--optimize`` fuses each
attention into one ``com.microsoft.MultiHeadAttention`` node (``prml2_edge.training.fusion``; onnxruntime's
offline transformer optimiser fuses none of them, and its other fusions measured slower than the ones
onnxruntime applies by itself), prints the fusions that applied and the largest difference from the
fp32 graph; with ``--int8`` (dynamic) the fused graph is then quantised (kept
beside it as ``<name>.opt.onnx``). The fp32 graph is kept beside a variant as ``<name>.fp32.onnx``.
Every variant runs on the edge install (onnxruntime only).
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

from prml2_edge import schema

HELP = "Export a trained checkpoint to ONNX for the edge runtime."
NEEDS: tuple[tuple[str, str], ...] = (("torch", "train"), ("onnx", "train"))

PARITY_TOL = 1e-4


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--checkpoint", required=True, metavar="CKPT",
                        help="checkpoint from prml2 train (best.pt), or a PRML2 .onnx file to re-export "
                             "(same weights and metadata; e.g. an older all-rows graph as a streaming one)")
    parser.add_argument("--out", required=True, metavar="ONNX", help="output .onnx file")
    parser.add_argument("--int8", nargs="?", const="dynamic", default=None, choices=("dynamic", "static"),
                        help="int8 quantisation, dynamic (the default when no value is given) or static (QDQ, "
                             "calibrated on simulated windows); reports the accuracy change")
    parser.add_argument("--calibration-windows", type=int, default=256, metavar="N",
                        help="simulated windows that calibrate --int8 static (default 256)")
    parser.add_argument("--optimize", action="store_true",
                        help="fuse each attention into one onnxruntime MultiHeadAttention node; prints which "
                             "fusions applied (combines with --int8 dynamic)")
    parser.add_argument("--data", metavar="DIR",
                        help="dataset for parity and int8 accuracy windows (validation split); required with --int8")
    parser.add_argument("--rows", default="1", metavar="N|all",
                        help="decoder steps the graph returns, the newest ones: 1 (default; all the streaming "
                             "runtime uses, and the cheapest graph) or 'all' (every one of the L - H)")
    parser.add_argument("--no-error-model", action="store_true",
                        help="do not measure the model's slow error on --data's validation split (by default the "
                             "omega_z variance inflation the calibrated filter applies is measured and stored)")
    parser.add_argument("--parity-windows", type=int, default=100, metavar="N",
                        help="windows for the torch/onnxruntime parity check (default 100, at least 100)")


def _windows(model, data_dir: str | None, n: int, seed: int = 0):
    """(n, L, 9) windows and their decoder z (n, L-H, 5) or None: validation windows when a dataset is given,
    otherwise random windows drawn from the model's normalisation statistics."""
    import numpy as np

    L, H = model.cfg.window_len, model.cfg.encoder_len
    if data_dir is None:
        rng = np.random.default_rng(seed)
        mean, std = model.in_mean.numpy(), model.in_std.numpy()
        return (mean + std * rng.normal(size=(n, L, len(mean)))).astype(np.float32), None
    from prml2_edge.data.datasets import load_dataset
    from prml2_edge.data.windows import build_windows

    dataset = load_dataset(data_dir)
    windows = build_windows([d for d in dataset.split("val") if d.has_ground_truth], L=L, H=H, stride=10)
    if len(windows) == 0:
        from prml2_edge.errors import DataError

        raise DataError(f"{data_dir}: the validation split has no full window of {L} samples")
    idx = np.linspace(0, len(windows) - 1, min(n, len(windows))).round().astype(int)
    onboard, z, _ = windows.get(idx)
    return onboard, z[:, H:]


def _rows(text: str, decoder_len: int) -> int | None:
    """``--rows``: None for 'all', else an int in [1, decoder_len] (ConfigError otherwise)."""
    from prml2_edge.errors import ConfigError

    if text.strip().lower() == "all":
        return None
    try:
        rows = int(text)
    except ValueError:
        rows = 0
    if not 1 <= rows <= decoder_len:
        raise ConfigError(f"--rows must be 'all' or a number from 1 to L - H = {decoder_len}, got {text!r}")
    return rows


def run(args: argparse.Namespace) -> int:
    import torch

    from prml2_edge.training.export_onnx import export_onnx, read_metadata

    torch.set_num_threads(2)
    out = _check_options(args)
    model, meta = _load_model(args.checkpoint)
    rows = _rows(args.rows, model.cfg.window_len - model.cfg.encoder_len)
    fp32_path = out.with_name(out.stem + ".fp32.onnx") if (args.int8 or args.optimize) else out
    export_onnx(model, meta, fp32_path, rows=rows)
    windows, z_dec = _windows(model, args.data, args.parity_windows)
    _check_parity(model, meta, fp32_path, windows, rows)
    if args.data and not args.no_error_model:
        _fit_error_model(fp32_path, args.data)
    source = fp32_path  # what --int8 quantises: the fp32 graph, or the fused one with --optimize
    if args.optimize:
        source = _optimize(fp32_path, out.with_name(out.stem + ".opt.onnx") if args.int8 else out, windows)
    if args.int8:
        _quantize(args, meta, fp32_path, source, out, windows, z_dec)
    read_metadata(out).check_schema(str(out))
    return 0


def _fit_error_model(path: Path, data_dir: str) -> None:
    """Measure the exported model's slow error on the validation split and store it in its metadata
    (:mod:`prml2_edge.evaluation.error_model`); a split too short for it gets one line, and no entry."""
    import onnx

    from prml2_edge.data.datasets import load_dataset
    from prml2_edge.evaluation import error_model
    from prml2_edge.evaluation.protocol import forget_model
    from prml2_edge.training.export_onnx import read_metadata, set_metadata

    try:
        entry = error_model.measure(str(path), load_dataset(data_dir))
    except ValueError as exc:
        print(f"error model: not measured ({exc}); the calibrated filter takes the model's variances as they are")
        return
    finally:
        forget_model(str(path))
    proto = onnx.load(str(path))
    set_metadata(proto, replace(read_metadata(path), error_model=entry))
    onnx.save(proto, str(path))
    names = ", ".join(f"{n} x{v:g}" for n, v in zip(schema.STATE_NAMES, entry["var_inflation"], strict=True))
    print(f"error model ({entry['window_s']:g} s means, {entry['source']}): variance inflation {names}; "
          "the calibrated filter applies omega_z's")


def _check_options(args: argparse.Namespace) -> Path:
    """Refuse option values and combinations that cannot work, before anything is loaded; the ``--out`` path."""
    from prml2_edge.errors import ConfigError

    if args.parity_windows < 100:
        raise ConfigError(f"--parity-windows must be at least 100, got {args.parity_windows}")
    if args.int8 and not args.data:
        raise ConfigError("--int8 needs --data DIR: the accuracy change is measured on its validation windows")
    if args.int8 == "static" and args.optimize:
        raise ConfigError("--optimize combines with --int8 dynamic only (static QDQ on the fused graph falls back "
                          "to float kernels in onnxruntime)")
    if args.int8 == "static" and args.calibration_windows < 1:
        raise ConfigError(f"--calibration-windows must be at least 1, got {args.calibration_windows}")
    out = Path(args.out)
    if out.suffix != ".onnx":
        raise ConfigError(f"--out must end in .onnx, got {out.name}")
    return out


def _load_model(checkpoint: str):
    """The model to export and its metadata: from a PRML2 or baseline checkpoint, or from an exported .onnx."""
    from prml2_edge.training.baselines.train import is_baseline_checkpoint, load_baseline
    from prml2_edge.training.checkpoint import load_model
    from prml2_edge.training.export_onnx import metadata_for, read_metadata

    if checkpoint.endswith(".onnx"):  # re-export an exported model (e.g. as a newest-row streaming graph)
        from prml2_edge import __version__
        from prml2_edge.training.export_onnx import model_from_onnx

        model, _, _ = model_from_onnx(checkpoint)
        return model, replace(read_metadata(checkpoint), version=__version__)
    model, ckpt = load_baseline(checkpoint) if is_baseline_checkpoint(checkpoint) else load_model(checkpoint)
    return model, metadata_for(model, ckpt)


def _check_parity(model, meta, fp32_path: Path, windows, rows: int | None) -> None:
    """Print the export and its torch/onnxruntime parity; ModelError beyond :data:`PARITY_TOL`."""
    from prml2_edge.errors import ModelError
    from prml2_edge.training.export_onnx import parity

    diff = parity(model, fp32_path, windows)
    print(f"exported {fp32_path} ({fp32_path.stat().st_size / 1e6:.2f} MB, preset {meta.preset}, input 1x{meta.L}x9, "
          f"output the newest {rows or meta.L - meta.H} decoder step(s))")
    print(f"parity torch vs onnxruntime on {diff['n']} windows: max |d mean| {diff['mean']:.2e}, "
          f"max |d var| {diff['var']:.2e} (tolerance {PARITY_TOL:.0e})")
    if not (diff["mean"] <= PARITY_TOL and diff["var"] <= PARITY_TOL):
        raise ModelError(f"onnxruntime output differs from torch by {max(diff['mean'], diff['var']):.2e}; "
                         "report this with the checkpoint")


def _optimize(fp32_path: Path, opt_path: Path, windows) -> Path:
    """``--optimize``: fuse the attentions into ``opt_path``, print the fusions and the difference; ``opt_path``."""
    from prml2_edge.training.quantize import max_output_difference, optimize_transformer

    fused = optimize_transformer(fp32_path, opt_path)
    diff = max_output_difference(fp32_path, opt_path, windows)
    applied = ", ".join(f"{k} {v}" for k, v in sorted(fused.items())) or "none"
    print(f"optimised: {opt_path} ({opt_path.stat().st_size / 1e6:.2f} MB); fusions applied: {applied}; "
          f"max |d mean| against the fp32 graph {diff['mean']:.2e}, max |d var| {diff['var']:.2e}")
    return opt_path


def _quantize(args: argparse.Namespace, meta, fp32_path: Path, source: Path, out: Path, windows, z_dec) -> None:
    """``--int8``: quantise into ``out`` (static: from ``fp32_path``; dynamic: from ``source``); print the z RMSE."""
    from prml2_edge.training.export_onnx import compare_int8, quantize_int8

    if args.int8 == "static":
        from prml2_edge.training.quantize import quantize_static_int8, simulated_windows

        calibration, _ = simulated_windows(args.calibration_windows, L=meta.L, H=meta.H)
        quantize_static_int8(fp32_path, out, calibration)
        how = f"static QDQ, calibrated on {len(calibration)} simulated windows"
    else:
        quantize_int8(source, out)
        how = "dynamic" + (", on the optimised graph" if args.optimize else "")
    report = compare_int8(fp32_path, out, windows, z_dec)
    print(f"int8 ({how}): {out} ({out.stat().st_size / 1e6:.2f} MB); z RMSE on {report['n_windows']} "
          "validation windows (before the guard), fp32 -> int8:")
    for name in report["fp32"]:
        a, b = report["fp32"][name], report["int8"][name]
        print(f"  {name:<14} {a:.4f} -> {b:.4f}  ({100 * (b - a) / a:+.1f} %)")
