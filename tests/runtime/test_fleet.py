"""``prml2 fleet`` on a real 2-worker Dask cluster bound to 127.0.0.1: per-log outputs, the summary table,
a corrupt log reported with its reason while the rest finish, and a second run that skips finished logs."""

from __future__ import annotations

import json
import os
import sys

import pytest

pytest.importorskip("distributed")

from prml2_edge.bench.replay_input import simulate_fleet_log  # noqa: E402
from prml2_edge.cli.main import main  # noqa: E402
from prml2_edge.fleet import SUMMARY, log_key  # noqa: E402
from prml2_edge.runtime.offline import run_offline  # noqa: E402
from prml2_edge.runtime.pipeline import Pipeline  # noqa: E402
from prml2_edge.runtime.source import scan_log  # noqa: E402


@pytest.fixture(scope="module")
def logs(tmp_path_factory):
    root = tmp_path_factory.mktemp("fleet_logs")
    good = [simulate_fleet_log(16.0, root / f"car{i}.log", seed=20 + i, gnss_head_s=4.0, gnss_tail_s=1.0)[0]
            for i in range(3)]
    cut = root / "cut.log"
    data = good[0].read_bytes()
    cut.write_bytes(data[: len(data) // 2 - 7])  # cut mid-line: the logger died
    return good, cut


def read_table(out):
    return json.loads((out / "fleet_summary.json").read_text())


def test_fleet_replays_every_log_reports_the_corrupt_one_and_resumes(logs, tmp_path, capsys):
    good, cut = logs
    out = tmp_path / "fleet"
    args = ["fleet", *map(str, good), str(cut), "--out", str(out), "--workers", "2"]
    assert main(args) == 1  # one log failed: non-zero exit, the others finished
    text = capsys.readouterr()
    assert "1 of 4 logs failed" in text.err
    doc = read_table(out)
    rows = {os.path.basename(r["log"]): r for r in doc["logs"]}
    assert [r["status"] for r in doc["logs"]] == ["ok", "ok", "ok", "failed"]
    assert "cut short" in rows["cut.log"]["reason"] and "cut.log" in text.out
    assert doc["totals"]["failed"] == 1 and doc["totals"]["ok"] == 3
    # each log's row is what an offline replay of it alone says
    direct = Pipeline.build()
    run_offline(direct, good[1], workers=1)
    s = direct.summary()
    r = rows["car1.log"]
    assert r["frames"] == scan_log(good[1])[0] == s["frames"]["received"]
    assert r["rejected"] == s["frames"]["rejected"]
    assert r["model_driven_pct"] == pytest.approx(100.0 * s["model_used_steps"] / s["rows"])
    assert r["hours"] == pytest.approx(s["data_s"] / 3600.0)
    assert r["drift_events"] == 1 and 0.0 < r["drift_pct"] < 50.0  # GNSS back after the outage
    assert doc["totals"]["frames"] == sum(rows[f"car{i}.log"]["frames"] for i in range(3))
    for log in good:
        folder = out / "logs" / log_key(log)
        assert (folder / SUMMARY).is_file() and (folder / "pose.tum").stat().st_size > 0
    assert (out / "logs" / log_key(cut) / "failed.json").is_file()
    assert (out / "fleet_summary.csv").read_text().count("\n") == 5

    # second run: finished logs are skipped (no cluster work), the failed one is tried again
    assert main(args) == 1
    doc2 = read_table(out)
    assert [r["status"] for r in doc2["logs"]] == ["skipped", "skipped", "skipped", "failed"]
    assert [r["frames"] for r in doc2["logs"]] == [r["frames"] for r in doc["logs"]]
    # a log that changed is replayed again
    os.utime(good[2], ns=(1, 1))
    assert main(["fleet", str(good[2]), "--out", str(out), "--workers", "1"]) == 0
    assert read_table(out)["logs"][0]["status"] == "ok"


def test_fleet_without_the_extra_says_what_to_install(monkeypatch, tmp_path, capsys):
    monkeypatch.setitem(sys.modules, "distributed", None)
    assert main(["fleet", "x.log", "--out", str(tmp_path)]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "'.[fleet]'" in err and "pip install" in err


def test_fleet_refuses_a_bad_model_before_starting_a_cluster(logs, tmp_path, capsys):
    assert main(["fleet", str(logs[0][0]), "--out", str(tmp_path), "--model", str(tmp_path / "no.onnx")]) == 1
    assert "model file not found" in capsys.readouterr().err


def test_fleet_on_an_existing_cluster_by_address(logs, tmp_path, capsys):
    from distributed import LocalCluster

    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True, host="127.0.0.1", dashboard_address=None,
                      scheduler_kwargs={"dashboard": False}) as cluster:
        out = tmp_path / "remote"
        assert main(["fleet", str(logs[0][1]), "--out", str(out), "--address", cluster.scheduler_address]) == 0
    assert cluster.scheduler_address in capsys.readouterr().out
    assert [r["status"] for r in read_table(out)["logs"]] == ["ok"]
    assert main(["fleet", str(logs[0][1]), "--out", str(out), "--address", "tcp://127.0.0.1:1", "--workers", "2"]) == 1
    assert "--workers sizes the local cluster" in capsys.readouterr().err
