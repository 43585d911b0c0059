"""Bad files and configuration: one line naming the file and the problem, non-zero exit, no traceback.

Also: a replay cut short by a damaged log still writes every pose it produced; a model pinned by
SHA-256 refuses any other file; nothing the runtime loads executes code.
"""

from __future__ import annotations

import ast
import hashlib
import json
import os
import pickle
from pathlib import Path

import pytest
from runtime_models import make_kinematic_model

from prml2_edge import schema
from prml2_edge.can.encode import encode_drive_to_log
from prml2_edge.cli.main import main
from prml2_edge.data.simulate import simulate_drive

FORMATS = (".log", ".asc", ".blf", ".csv", ".trc", ".log.gz")


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    root = tmp_path_factory.mktemp("files")
    drive = simulate_drive(0.1, 1.0, 2)  # 6 s
    logs = {}
    for suffix in FORMATS:
        logs[suffix] = root / f"drive{suffix}"
        encode_drive_to_log(drive, logs[suffix], gnss_seconds=1.0)
    return root, logs, make_kinematic_model(root / "kinematic.onnx"), drive


def one_line_error(capsys, *needles: str) -> str:
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    for needle in needles:
        assert needle in err, err
    return err


def replay_args(log: Path, model: Path, out: Path, *extra: str) -> list[str]:
    return ["replay", str(log), "--model", str(model), "--jsonl", str(out / "p.jsonl"),
            "--summary-json", str(out / "s.json"), *extra]


def _damage(raw: bytes, how: str, suffix: str) -> bytes:
    if how == "truncated":  # mid-line: a cut exactly at a line end is just a shorter log
        return raw[: int(len(raw) * 0.6) + 7]
    mid = len(raw) // 2
    return raw[:mid] + bytes((b * 7 + 13) % 256 for b in range(256)) + raw[mid + 256:]


@pytest.mark.parametrize("suffix", FORMATS)
@pytest.mark.parametrize("how", ["truncated", "corrupt"])
def test_a_damaged_log_fails_in_one_line_and_keeps_every_pose_it_produced(files, capsys, tmp_path, suffix, how):
    _, logs, model, _ = files
    bad = tmp_path / f"bad{suffix}"
    bad.write_bytes(_damage(logs[suffix].read_bytes(), how, suffix))
    assert main(replay_args(bad, model, tmp_path)) == 1
    err = one_line_error(capsys, str(bad))
    assert "cut short" in err or "cannot read CAN log" in err or "holds no frames" in err
    if (tmp_path / "s.json").exists():  # frames before the damage were replayed
        summary = json.loads((tmp_path / "s.json").read_text())
        rows = (tmp_path / "p.jsonl").read_text().splitlines()
        assert summary["rows"] == len(rows) and summary["frames"]["balanced"]
        if how == "truncated":
            assert len(rows) > 50  # 60 % of the file is well over a second of driving
            assert all(json.loads(r)["t_s"] is not None for r in rows)
    else:
        assert how == "corrupt"  # nothing readable before the damage (compressed formats)


def test_an_intact_log_of_every_format_is_not_reported_as_cut_short(files):
    from prml2_edge.runtime.source import scan_log

    _, logs, _, _ = files
    for path in logs.values():
        n, _, _, problem = scan_log(path)
        assert problem is None and n > 1000, (path, problem)


def test_a_dbc_that_does_not_parse(files, capsys, tmp_path):
    _, logs, model, _ = files
    bad = tmp_path / "broken.dbc"
    bad.write_text('VERSION ""\n\nBO_ 160 WHEEL_SPEEDS_FRONT: 8 ESP\n SG_ CHECKSUM : 0|8@1+ (1,0) [0|255 "" X\n')
    assert main(replay_args(logs[".log"], model, tmp_path, "--dbc", str(bad))) == 1
    one_line_error(capsys, str(bad), "DBC does not parse")


def test_a_map_naming_signals_the_dbc_lacks(files, capsys, tmp_path, repo_root):
    _, logs, model, _ = files
    text = (repo_root / "dbc" / "maps" / "prml2_onboard.toml").read_text()
    text = text.replace('signal = "YAW_RATE"', 'signal = "YAW_RATE_FILTERED"')
    text = text.replace('dbc = "prml2_onboard.dbc"', f'dbc = "{repo_root / "dbc" / "prml2_onboard.dbc"}"')
    bad = tmp_path / "wrong_map.toml"
    bad.write_text(text)
    assert main(replay_args(logs[".log"], model, tmp_path, "--map", str(bad))) == 1
    one_line_error(capsys, str(bad), "ESP_YAW_LAT.YAW_RATE_FILTERED not in DBC")


def test_unknown_keys_in_the_map_and_the_runtime_config(files, capsys, tmp_path, repo_root):
    _, logs, model, _ = files
    text = (repo_root / "dbc" / "maps" / "prml2_onboard.toml").read_text()
    text = text.replace("rate_hz = 25.0", "rate_hz = 25.0\nrate_hertz = 25.0")
    text = text.replace('dbc = "prml2_onboard.dbc"', f'dbc = "{repo_root / "dbc" / "prml2_onboard.dbc"}"')
    (tmp_path / "typo_map.toml").write_text(text)
    assert main(replay_args(logs[".log"], model, tmp_path, "--map", str(tmp_path / "typo_map.toml"))) == 1
    one_line_error(capsys, "typo_map.toml", "unknown key 'rate_hertz'")
    (tmp_path / "runtime.toml").write_text('[signals]\nstale_period = 3.0\n')
    assert main(replay_args(logs[".log"], model, tmp_path, "--config", str(tmp_path / "runtime.toml"))) == 1
    one_line_error(capsys, "runtime.toml", "unknown key 'stale_period'")
    (tmp_path / "notoml.toml").write_text('[signals\nmu = 1\n')
    assert main(replay_args(logs[".log"], model, tmp_path, "--config", str(tmp_path / "notoml.toml"))) == 1
    one_line_error(capsys, "notoml.toml", "not valid TOML")


def test_a_model_whose_metadata_does_not_match_the_map(files, capsys, tmp_path):
    _, logs, _, _ = files
    names = list(schema.SIGNAL_NAMES)
    names[5], names[2] = names[2], names[5]
    bad = make_kinematic_model(tmp_path / "swapped.onnx", meta_overrides={"signal_names": names})
    assert main(replay_args(logs[".log"], bad, tmp_path)) == 1
    one_line_error(capsys, str(bad), "signal order differs", "yaw_rate_radps")


def test_a_model_file_that_is_not_onnx_is_refused_and_never_executed(files, capsys, tmp_path):
    _, logs, _, _ = files
    junk = tmp_path / "junk.onnx"
    junk.write_bytes(os.urandom(4096))
    assert main(replay_args(logs[".log"], junk, tmp_path)) == 1
    one_line_error(capsys, str(junk), "cannot load the model")

    marker = tmp_path / "pwned"

    class Payload:
        def __reduce__(self):
            return (Path.touch, (marker,))

    evil = tmp_path / "evil.onnx"
    evil.write_bytes(pickle.dumps(Payload()))
    assert main(replay_args(logs[".log"], evil, tmp_path)) == 1
    one_line_error(capsys, str(evil), "cannot load the model")
    assert not marker.exists()  # the pickle was never unpickled


def test_debug_lets_the_exception_through_with_its_cause(files, tmp_path):
    from prml2_edge.errors import ModelError

    _, logs, _, _ = files
    junk = tmp_path / "junk.onnx"
    junk.write_bytes(b"not a model")
    with pytest.raises(ModelError, match="cannot load the model") as info:
        main(["--debug", *replay_args(logs[".log"], junk, tmp_path)])
    assert info.value.__cause__ is not None  # the onnxruntime error, for the traceback


def test_a_pinned_model_runs_and_any_other_file_is_refused(files, capsys, tmp_path):
    _, logs, model, _ = files
    digest = hashlib.sha256(model.read_bytes()).hexdigest()
    cfg = tmp_path / "pinned.toml"
    cfg.write_text(f'[model]\npath = "{model}"\nsha256 = "{digest}"\n')
    assert main(["replay", str(logs[".log"]), "--config", str(cfg)]) == 0
    capsys.readouterr()
    other = make_kinematic_model(tmp_path / "other.onnx", std=(0.2, 0.05, 0.5, 0.3, 0.01))
    assert main(["replay", str(logs[".log"]), "--config", str(cfg), "--model", str(other)]) == 1
    one_line_error(capsys, str(other), "does not match the pinned", digest)


RUNTIME_DIRS = ("runtime", "can", "ekf")
RUNTIME_FILES = ("config.py", "schema.py", "model_meta.py", "guard.py", "errors.py", "resources.py")
CODE_LOADERS = {"pickle", "cPickle", "dill", "joblib", "marshal", "shelve", "torch", "yaml"}


def test_nothing_the_runtime_loads_executes_code(repo_root):
    """No pickle-like loader, eval/exec, or np.load with pickles anywhere in the runtime's modules."""
    pkg = repo_root / "prml2_edge"
    paths = [p for d in RUNTIME_DIRS for p in (pkg / d).rglob("*.py")] + [pkg / f for f in RUNTIME_FILES]
    assert len(paths) > 15
    for path in paths:
        tree = ast.parse(path.read_text(), str(path))
        for node in ast.walk(tree):
            if isinstance(node, ast.Import | ast.ImportFrom):
                names = [a.name for a in node.names] + ([node.module] if isinstance(node, ast.ImportFrom) else [])
                assert not {str(n).split(".")[0] for n in names} & CODE_LOADERS, (path, names)
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Name):
                assert node.func.id not in ("eval", "exec", "compile", "__import__"), path
            if isinstance(node, ast.keyword) and node.arg == "allow_pickle":
                assert isinstance(node.value, ast.Constant) and node.value.value is False, path
