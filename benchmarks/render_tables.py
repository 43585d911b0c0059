"""Re-render the result tables of the docs from the benchmark JSON in ``benchmarks/results/``.

    .venv/bin/python benchmarks/render_tables.py           # rewrite every block whose JSON is there
    .venv/bin/python benchmarks/render_tables.py --check   # exit 1 when a page would change

A block in a page under ``docs/`` is ``<!-- results:NAME -->`` ... ``<!-- /results -->``, NAME a key of
``RENDERERS``. Its text becomes the table rendered from ``benchmarks/results/<file>.json`` and a "Source:" line
with the commit and the command that produced it (``machine.commit`` and ``machine.command``, written by
``prml2_edge.bench.machine.machine_info``). A block whose JSON is missing keeps its text: that is how the
hand-written tables of runs whose JSON was not kept stay (``benchmarks/results/*.json`` is git-ignored).
``latency.py``, ``replay_throughput.py``, ``training_throughput.py`` and ``reliability.py`` call ``render()``
when they finish; for the other scripts run this by hand.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from collections.abc import Callable
from pathlib import Path

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results"
DOCS = HERE.parent / "docs"
BLOCK = re.compile(r"(<!-- results:([\w-]+) -->\n)(.*?)(<!-- /results -->)", re.S)


def _n(x: float) -> str:
    """An integer with thin grouping: 1 533 050."""
    return f"{int(x):,}".replace(",", " ")


def _yes(ok: bool) -> str:
    return "yes" if ok else "**no**"


def latency(doc: dict) -> list[str]:
    import report
    return report.targets_markdown(doc) + [""] + report.latency_markdown(doc)


def throughput(replay: dict | None, training: dict | None) -> list[str]:
    import report
    return report.throughput_markdown(replay, training)


def reliability(doc: dict) -> list[str]:
    import reliability as rel  # the runtime's imports: only when there is a reliability.json
    return rel.markdown(doc)


def soak(doc: dict) -> list[str]:
    out = [f"{doc['drive_minutes']:g} min of driving, {doc['faults_scheduled']} faults, stride {doc['stride']}.", "",
           "| cross-checks | frames | used / ignored / rejected | balanced | non-finite poses | inference failures "
           "| EKF resets | e2e p50 / p99 [ms] | plausibility stage p99 [ms] | RSS [MiB] |",
           "|---|---:|---|---|---:|---:|---:|---:|---:|---|"]
    for name, r in doc["runs"].items():
        rss = r["rss_mib"]
        pl = "–" if r.get("plausibility_p99_ms") is None else f"{r['plausibility_p99_ms']:.2f}"
        half = r.get("rss_growth_second_half_mib")
        out.append(f"| {name} | {_n(r['frames'])} | {_n(r['used'])} / {_n(r['ignored'])} / {_n(r['rejected'])} | "
                   f"{_yes(r['balanced'])} | {r['nonfinite_poses']} | {r['inference_failures']} | {r['ekf_resets']} | "
                   f"{r['e2e_p50_ms']:.2f} / {r['e2e_p99_ms']:.2f} | {pl} | {rss[0]['rss_mib']:.0f} → "
                   f"{rss[-1]['rss_mib']:.0f}" + ("" if half is None else f" ({half:+.1f} in the 2nd half)") + " |")
    if "e2e_p99_increase_ms" in doc:
        out += ["", f"p99 with the checks on minus off: {doc['e2e_p99_increase_ms']:+.2f} ms (target <= +0.3 ms: "
                    f"{_yes(doc['e2e_p99_target_met'])})."]
    return out


def fuzz(doc: dict) -> list[str]:
    return ["| frames | used | ignored | rejected | balanced | non-finite poses | raised | wall [s] |",
            "|---:|---:|---:|---:|---|---:|---|---:|",
            f"| {_n(doc['received'])} | {_n(doc['used'])} | {_n(doc['ignored'])} | {_n(doc['rejected'])} | "
            f"{_yes(doc['balanced'])} | {doc['nonfinite_poses']} | {doc['exception'] or 'nothing'} | "
            f"{doc['wall_s']:g} |"]


def calibration_replay(doc: dict) -> list[str]:
    out = ["| seed | drift % (cal) | drift % (no cal) | RMSE m (cal) | RMSE m (no cal) | 2σ / 3σ % (cal) | "
           "2σ / 3σ % (no cal) | yaw offset at outage °/s | wheel scale at outage % |",
           "|---|---|---|---|---|---|---|---|---|"]

    def row(seed: str, on: dict, off: dict, yaw: float, scale: float, b: str = "") -> str:
        """One table row; ``b = "**"`` makes the figures bold (the mean)."""
        cov = [f"{d.get('coverage_2sigma_pct', 0):.0f} / {d.get('coverage_3sigma_pct', 0):.0f}" for d in (on, off)]
        cells = [seed, f"{on['drift_pct']:.2f}", f"{off['drift_pct']:.2f}", f"{on['rmse_m']:.1f}",
                 f"{off['rmse_m']:.1f}", *cov]
        return "| " + " | ".join(f"{b}{c}{b}" for c in cells) + f" | {yaw:+.3f} | {scale:+.2f} |"
    for r in doc["drives"]:
        cal = r["calibrated"].get("calibration_at_outage", {})
        out.append(row(str(r["seed"]), r["calibrated"], r["reference"], cal.get("yaw_rate_offset_dps", float("nan")),
                       cal.get("wheel_scale_pct", float("nan"))))
    s = doc["summary"]
    out.append(row("mean", s["calibrated"], s["reference"], s["calibrated"]["yaw_offset_estimate_dps"],
                   s["calibrated"]["wheel_scale_estimate_pct"], "**"))
    return out


def calibration_replay_highway(doc: dict) -> list[str]:
    truth = doc["args"]["yaw_offset_dps"]
    out = [f"| car | genuine fixes refused | refused without calibration | yaw offset at outage °/s (truth "
           f"{truth:+.3f}) | drift % | drift % without calibration | 2σ / 3σ % |", "|---|---|---|---|---|---|---|"]
    for r in doc["cars"]:
        on, off = r["calibrated"], r["reference"]
        std = (on.get("calibration") or {}).get("yaw_rate_offset_std_dps", float("nan"))
        out.append(f"| {r['car']} | {on['refused']} of {r['fixes']} | {off['refused']} | "
                   f"{r['yaw_offset_estimate_dps']:+.3f} ± {std:.3f} | {on['truth']['drift_pct']:.2f} | "
                   f"{off['truth']['drift_pct']:.2f} | {on['truth'].get('coverage_2sigma_pct', 0):.0f} / "
                   f"{on['truth'].get('coverage_3sigma_pct', 0):.0f} |")
    s = doc["summary"]
    out.append(f"| **mean** | **{s['refused_total']}** | | | **{s['mean_drift_pct']:.2f}** | "
               f"**{s['mean_drift_pct_without_calibration']:.2f}** | |")
    return out


def sim_realism(doc: dict) -> list[str]:
    cars = list(doc["rows"][0]["cars"])
    out = ["| variant | split | " + " | ".join(f"`{c}`" for c in cars) + " | fleet |",
           "|---|---|" + "---|" * (len(cars) + 1)]
    for r in doc["rows"]:
        cells = [f"{r['cars'][c]['rmse_mean_m']:.1f} ({r['cars'][c]['drift_mean_pct']:.2f} %)" for c in cars]
        f = r["fleet"]
        out.append(f"| {r['variant']} | {r['split']} | " + " | ".join(cells) +
                   f" | **{f['rmse_mean_m']:.1f} ± {f['rmse_std_m']:.1f}** ({f['drift_mean_pct']:.2f} %) |")
    return out


def sensor_profile(doc: dict) -> list[str]:
    out = ["| signal | unit | step real / sim | hold median real / sim | hold p90 real / sim | changing samples real / "
           "sim | p5..p95 real | p5..p95 sim |", "|---|---|---|---|---|---|---|---|"]
    for r in doc["rows"]:
        out.append(f"| {r['column']} | {r['unit']} | {r['step_real']:g} / {r['step_sim']:g} | "
                   f"{r['hold_median_real']:g} / {r['hold_median_sim']:g} | {r['hold_p90_real']:g} / "
                   f"{r['hold_p90_sim']:g} | {r['change_real']:.2f} / {r['change_sim']:.2f} | "
                   f"{r['range_real'][0]:.2f}..{r['range_real'][1]:.2f} | "
                   f"{r['range_sim'][0]:.2f}..{r['range_sim'][1]:.2f} |")
    sp = doc["speedometer_ratio"]
    return out + ["", f"Speedometer / mean wheel speed: real {sp['real']:.3f}, simulated {sp['sim']:.3f}."]


def robustness(doc: dict) -> list[str]:
    import robustness as rob  # the evaluation's imports: only when there is a robustness.json
    return rob.markdown(doc)


# block name -> (JSON files it reads, renderer taking one document per file, None where the file is missing)
def cue_consistency(doc: dict) -> list[str]:
    import cue_consistency as cc
    return cc.markdown(doc)


def filter_ablation(doc: dict) -> list[str]:
    import filter_ablation as fa
    return fa.markdown(doc)


def error_budget(doc: dict) -> list[str]:
    import error_budget as eb
    return eb.markdown(doc)


RENDERERS: dict[str, tuple[tuple[str, ...], Callable[..., list[str]]]] = {
    "latency": (("latency",), latency),
    "throughput": (("replay", "training"), throughput),
    "reliability": (("reliability",), reliability),
    "soak": (("soak",), soak),
    "fuzz": (("fuzz",), fuzz),
    "calibration_replay": (("calibration_replay",), calibration_replay),
    "calibration_replay_highway": (("calibration_replay_highway",), calibration_replay_highway),
    "sim_realism": (("sim_realism",), sim_realism),
    "sensor_profile": (("sensor_profile",), sensor_profile),
    "robustness": (("robustness",), robustness),
    "robustness_cal": (("robustness_cal",), robustness),  # --calibration: the runtime's filter
    "robustness_cal_dep": (("robustness_cal_dep",), robustness),  # --calibration --preroll-s 30
    "cue_consistency": (("cue_consistency",), cue_consistency),
    "filter_ablation": (("filter_ablation",), filter_ablation),
    "error_budget": (("error_budget",), error_budget),
}


def source_line(docs: dict[str, dict], results: Path = RESULTS) -> str:
    """``Source: `COMMAND` at commit `COMMIT` (DATE) ...`` for each result that went into a table."""
    where = results.resolve()
    where = where.relative_to(HERE.parent) if where.is_relative_to(HERE.parent) else where
    parts = []
    for name, doc in docs.items():
        m = doc.get("machine") or {}
        command = m.get("command") or doc.get("command") or "unknown command"
        when = doc.get("started") or doc.get("date")
        parts.append(f"`{command}` at commit `{m.get('commit') or 'unknown'}`" + (f" ({when})" if when else "")
                     + f", `{(where / f'{name}.json').as_posix()}`")
    return "Source: " + "; ".join(parts) + ". Rendered by `benchmarks/render_tables.py`."


def render_text(text: str, results: Path = RESULTS) -> str:
    """``text`` with every block whose JSON is in ``results`` re-rendered (the others as they were)."""
    def block(m: re.Match) -> str:
        files, fn = RENDERERS.get(m.group(2), ((), None))
        docs = {f: json.loads((results / f"{f}.json").read_text()) for f in files if (results / f"{f}.json").is_file()}
        if fn is None or not docs:
            return m.group(0)
        lines = fn(*(docs.get(f) for f in files))
        return m.group(1) + "\n".join(lines) + "\n\n" + source_line(docs, results) + "\n" + m.group(4)
    return BLOCK.sub(block, text)


def render(docs: Path = DOCS, results: Path = RESULTS, check: bool = False) -> list[Path]:
    """Re-render every page under ``docs``; the pages that changed (with ``check``, would change; none written)."""
    if str(HERE) not in sys.path:
        sys.path.insert(0, str(HERE))  # report.py, reliability.py
    changed = []
    for page in sorted(docs.rglob("*.md")):
        text = page.read_text()
        new = render_text(text, results)
        if new != text:
            changed.append(page)
            if not check:
                page.write_text(new)
    return changed


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--docs", default=str(DOCS), help="folder of the pages (default docs/)")
    ap.add_argument("--results", default=str(RESULTS), help="folder of the JSON (default benchmarks/results/)")
    ap.add_argument("--check", action="store_true", help="change nothing; exit 1 when a page is out of date")
    args = ap.parse_args(argv)
    changed = render(Path(args.docs), Path(args.results), check=args.check)
    for page in changed:
        print(f"{'out of date' if args.check else 'rewrote'}: {page}")
    return 1 if args.check and changed else 0


if __name__ == "__main__":
    sys.exit(main())
