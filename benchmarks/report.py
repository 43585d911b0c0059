"""Render benchmark results (``benchmarks/results/*.json``) as text and as the tables in ``docs/benchmarks.md``."""

from __future__ import annotations

from pathlib import Path

import targets as tg

from prml2_edge.bench.results import write_json


def _config_target(c: dict) -> float | None:
    if c["runtime"] not in tg.RUNTIME_CONFIGS:
        return None
    if c["model"] == "paper":
        return tg.PAPER_FP32_P99_MS if c["precision"] == "fp32" else tg.PAPER_REDUCED_P99_MS
    return tg.EDGE_P99_MS


def _yes(met: bool | None) -> str:
    return "-" if met is None else ("yes" if met else "**no**")


def latency_lines(doc: dict) -> list[str]:
    """Terminal summary of a latency result."""
    lines = [f"{'config':<26} {'steps':>6} {'e2e p50':>8} {'p95':>7} {'p99':>7} {'max':>7}  {'model p50':>9} "
             f"{'ovh p99':>7}  {'outside p50/p99':>15}  {'GFLOP/s':>7}  load"]
    for c in doc["configs"]:
        e, m, o = c["e2e_ms"], c["model_ms"], c["overhead_ms"]
        lines.append(f"{c['name']:<26} {c['steps']:>6} {e['p50']:>8.2f} {e['p95']:>7.2f} {e['p99']:>7.2f} "
                     f"{e['max']:>7.2f}  {m['p50']:>9.2f} {o['p99']:>7.2f}  {_outside(c):>15}  "
                     f"{c['model_gflops_per_s']:>7.1f}  {c.get('load', '')}")
    lines.append(f"outside: decode + assemble (the row's frames) + plausibility + guard + filter + sinks per row [ms]; "
                 f"whole run: {doc.get('load', 'load unknown')}")
    for t in doc["targets"]:
        lines.append(f"target: {t['target']}: {t['measured']} -> {_yes(t['met'])}")
    return lines


def _outside(c: dict) -> str:
    """``p50 / p99`` [ms] of everything outside the model per row (bench.latency), ``-`` where not measured."""
    o = c.get("outside_ms") or {}
    return f"{o['p50']:.3f} / {o['p99']:.3f}" if o.get("count") else "-"


def _machine_line(m: dict) -> str:
    return (f"{m['cpu_model']}, {m['cores_usable']} usable cores, flags {', '.join(m['flags'])}; "
            f"numpy {m['numpy']} (BLAS {m['blas'].get('core')}), onnxruntime {m['onnxruntime']}, "
            f"torch {m.get('torch')}, Python {m['python']}")


def latency_markdown(doc: dict) -> list[str]:
    quick = " -- QUICK development run (short drives), not the full benchmark" if doc.get("quick") else ""
    out = [f"### Latency per 50 Hz step ({doc['started']}){quick}", "",
           f"Machine: {_machine_line(doc['machine'])}. Load average at start {doc['machine']['load_average']}, "
           f"at end {doc['load_average_end']}: {doc.get('load', 'load unknown')}.", ""]
    for name, info in doc["models"].items():
        out.append(f"- **{name}**: {info['source']}; {info['flops']['total'] / 1e9:.3f} GFLOP per inference.")
    out += ["", "| configuration | steps | e2e p50 | p95 | p99 | max | model-only p50 / p99 | overhead p50 / p99 "
                "| outside the model p50 / p99 | model GFLOP/s | target (e2e p99) | met? | load |",
            "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|---|"]
    for c in doc["configs"]:
        e, m, o = c["e2e_ms"], c["model_ms"], c["overhead_ms"]
        t = _config_target(c)
        met = None if t is None else e["p99"] <= t
        tgt = f"<= {t:g} ms" if t is not None else "reference"
        out.append(f"| {c['name']} | {c['steps']} | {e['p50']:.2f} | {e['p95']:.2f} | {e['p99']:.2f} | "
                   f"{e['max']:.2f} | {m['p50']:.2f} / {m['p99']:.2f} | {o['p50']:.2f} / {o['p99']:.2f} | "
                   f"{_outside(c)} | {c['model_gflops_per_s']:.1f} | {tgt} | {_yes(met)} | {c.get('load', '-')} |")
    lo, hi = doc["paper_orin_infer_ms"]
    out.append(f"| paper (Sec. V): PRML2 on an NVIDIA Orin GPU | - | - | - | - | - | {lo:g}-{hi:g} (inference) "
               "| - | - | - | ~30 Hz | - | - |")
    out += ["", "Times in ms. e2e: from the receipt of the CAN frame that completes a 50 Hz row to the EKF output "
                "(decode, assemble, window, ONNX/torch model, guard, EKF). `torch-*`: the plain PyTorch eager pipeline "
                "(same frames, interleaved in the same run).", "",
            "| hardware | 1 thread | 2 threads |", "|---|---:|---:|"]
    g = doc["gemm"]
    out.append("| NumPy fp32 GEMM on the paper model's shapes [GFLOP/s] | "
               + " | ".join(f"{g[k]['flop_weighted_gflops']:.1f}" if k in g else "-" for k in ("1", "2")) + " |")
    fr = {f["name"]: f for f in doc["fraction_of_gemm"]}
    for model in doc["models"]:
        for rt in ("onnx", "torch"):
            cells = []
            for k in ("1", "2"):
                f = fr.get(f"{model}-{rt}-fp32-{k}t")
                cells.append(f"{f['model_gflops_per_s']:.1f} ({100 * f['fraction']:.0f} %)" if f else "-")
            out.append(f"| {model} {rt} fp32 model rate [GFLOP/s] (fraction of GEMM) | " + " | ".join(cells) + " |")
    for r in doc["ratios"]:
        out.append(f"| {r['model']}: torch eager / runtime, {r['threads']} thread(s) | e2e p50 {r['e2e_p50']:.2f}x, "
                   f"p99 {r['e2e_p99']:.2f}x | model p50 {r['model_p50']:.2f}x |")
    rm = doc.get("int8_rmse") or {}
    for model, res in rm.items():
        if not res:
            continue
        for label, r in res.items():
            ch = ", ".join(f"{k} {100 * v:+.1f} %" for k, v in r["relative_change"].items())
            out.append(f"| {model} {label} z RMSE change vs fp32 ({r['n_windows']} test windows) | {ch} | |")
    return out


def throughput_markdown(replay: dict | None, training: dict | None) -> list[str]:
    out = ["### Throughput", "", "| measurement | value | target | met? |", "|---|---:|---:|---|"]
    if replay:
        for r in replay["runs"]:
            rss = r["rss"]
            where = ", ".join(f"{k} {v:.2f}" for k, v in r["per_row_ms"].items())
            mode = r.get("mode", "streaming")
            if mode == "streaming":
                what, target = f"{r['threads']} thread(s)", tg.REPLAY_X_REALTIME
                met = _yes(r["x_realtime"] >= target)
            else:
                what = f"offline ({r['precision']}, {r['workers']} inference worker(s))"
                target = tg.OFFLINE_X_REALTIME if r["precision"] == "fp32" else tg.OFFLINE_REDUCED_X_REALTIME
                met = _yes(r["x_realtime"] >= target)
                if "z_rmse_change" in r:
                    worst = max(abs(v) for v in r["z_rmse_change"].values())
                    where += f"; z RMSE change vs fp32 at most {100 * worst:.2f} %"
                    met = _yes(r["x_realtime"] >= target and worst <= tg.OFFLINE_REDUCED_RMSE_CHANGE)
            vs = ""
            if "x_vs_streaming" in r and mode != "streaming":
                vs = f", {r['x_vs_streaming']:.2f} x the streaming replay"
            cpu = ""
            if "cpu_ms_per_driven_s" in r:
                cpu = (f"; CPU {r['cpu_ms_per_driven_s']:.1f} ms per driven s, so on 2 idle cores "
                       f"{r['x_realtime_2_idle_cores_from_cpu']:.1f} x")
            load = r.get("load") or f"load {r['load_average'][0]}"  # (older results: no label)
            out.append(f"| replay of a {replay['drive_minutes']:g}-minute drive, {replay['model']} model, "
                       f"{what}, stride 1 ({replay['started']}, {load}) "
                       f"| {r['x_realtime']:.1f} x real time{vs} ({r['rows_per_s']:.0f} rows/s{cpu}; per row [ms]: "
                       f"{where}) | >= {target:g} x | {met} |")
            workers = f", inference workers {rss['workers_peak_mib']:.0f} MiB at most" if rss.get("workers_peak_mib") \
                else ""
            out.append(f"| RSS over that replay: start {rss['start_mib']:.0f} MiB, half-way {rss['half_mib']:.0f}, "
                       f"end {rss['end_mib']:.0f}, peak {rss['peak_mib']:.0f}{workers} | growth in the 2nd half "
                       f"{rss['second_half_growth_mib']:.1f} MiB ({100 * rss['second_half_growth_fraction']:.1f} %) "
                       f"| <= {100 * tg.RSS_GROWTH_FRACTION:g} % (flat) | {_yes(rss['flat'])} |")
    if training:
        for p in training["presets"]:
            out.append(f"| training throughput, {p['preset']} preset, batch {p['batch_size']} "
                       f"({training['started']}) | pretraining {p['pretrain_windows_per_s']:.1f} windows/s, "
                       f"EKF fine-tuning {p['finetune_windows_per_s']:.1f} windows/s | - | - |")
    return out


def targets_markdown(latency: dict | None) -> list[str]:
    if not latency:
        return []
    out = ["### Targets (issue 7, 2 cores of this machine)", "", "| target | measured | met? | configuration |",
           "|---|---|---|---|"]
    for t in latency["targets"]:
        out.append(f"| {t['target']} | {t['measured']} | {_yes(t['met'])} | {t['config'] or '-'} |")
    return out


def save(doc: dict, out: str | Path, update: bool = True) -> Path:
    """Write a result ``doc`` as JSON to ``out`` and, unless ``update`` is False, refresh the docs' tables."""
    out = write_json(doc, out)
    if update:
        update_readme()
    return out


def update_readme() -> None:
    """Re-render the result tables in the docs pages from ``benchmarks/results/`` (``render_tables.py``)."""
    import render_tables

    render_tables.render()
