"""Runtime TOML configuration: every option loads, unknown keys and wrong types are refused by name."""

import dataclasses

import pytest

from prml2_edge.config import (
    RuntimeConfig,
    config_from_dict,
    load_config,
    sha256_file,
    verify_pinned_model,
    with_overrides,
)
from prml2_edge.errors import ConfigError, ModelError


def test_shipped_example_lists_every_option(repo_root):
    cfg = load_config(repo_root / "deploy" / "runtime.toml")
    assert cfg.can.interface == "socketcan" and cfg.model.providers == ("tensorrt", "cuda", "cpu")
    text = (repo_root / "deploy" / "runtime.toml").read_text()
    for section in dataclasses.fields(RuntimeConfig):
        assert f"[{section.name}]" in text
        for opt in dataclasses.fields(getattr(RuntimeConfig(), section.name)):
            assert opt.name in text, f"[{section.name}] {opt.name} missing from deploy/runtime.toml"


@pytest.mark.parametrize("doc, message", [
    ({"can": {"bitrat": 500000}}, r"unknown key 'bitrat'"),
    ({"cann": {}}, r"unknown key 'cann'"),
    ({"can": {"bitrate": "fast"}}, r"\[can\] bitrate: expected int"),
    ({"model": {"threads": True}}, r"\[model\] threads: expected int"),
    ({"model": {"providers": "cpu"}}, r"\[model\] providers: expected a list"),
    ({"model": {"threads": 0}}, r"threads must be >= 1"),
    ({"model": {"spinning": "yes"}}, r"\[model\] spinning: expected bool"),
    ({"model": {"sha256": "abc"}}, r"64 hex digits"),
    ({"signals": {"mu": -1}}, r"mu must be > 0"),
    ({"signals": {"driven_axle": "rwd"}},
     r"\[signals\] driven_axle must be one of front, rear, all \(FWD, RWD, AWD\), got 'rwd'$"),
    ({"signals": {"steering_ratio": 0}}, r"steering_ratio must be > 0"),
    ({"initial_pose": {"source": "magic"}}, r"source must be one of"),
    ({"sinks": "x"}, r"\[sinks\]: expected a table"),
    ({"gnss": {"reciever": "gpsd://localhost"}},
     r"^cfg.toml: gnss: unknown key 'reciever' \(known: course, file, origin, receiver, time_offset_s\)$"),
    ({"gnss": {"origin": [48.1]}}, r"\[gnss\] origin must be \[LAT, LON\]"),
    ({"gnss": {"origin": [148.1, 11.5]}}, r"latitude within \+-90"),
    ({"gnss": {"origin": "48.1,11.5"}}, r"\[gnss\] origin: expected a list of float"),
    ({"gnss": {"time_offset_s": "1 h"}}, r"\[gnss\] time_offset_s: expected float"),
])
def test_bad_values_are_named(doc, message):
    with pytest.raises(ConfigError, match=message):
        config_from_dict(doc, "cfg.toml")


def test_ints_are_accepted_for_floats_and_overrides_apply(tmp_path):
    p = tmp_path / "r.toml"
    p.write_text('[signals]\nmu = 1\n[can]\ninterface = "virtual"\n')
    cfg = load_config(p)
    assert cfg.signals.mu == 1.0 and isinstance(cfg.signals.mu, float)
    cfg2 = with_overrides(cfg, can={"channel": "vcan0", "interface": None}, model={"threads": 2})
    assert cfg2.can.channel == "vcan0" and cfg2.can.interface == "virtual" and cfg2.model.threads == 2
    with pytest.raises(ConfigError, match="not valid TOML"):
        p.write_text("[can\n")
        load_config(p)


def test_model_pinning(tmp_path):
    model = tmp_path / "m.onnx"
    model.write_bytes(b"model bytes")
    digest = sha256_file(model)
    assert verify_pinned_model(model, digest.upper()) == digest
    assert verify_pinned_model(model, None) == digest
    with pytest.raises(ModelError, match="does not match the pinned"):
        verify_pinned_model(model, "0" * 64)


def test_spinning_reaches_the_onnxruntime_session(tmp_path):
    """[model] spinning (and --spinning over it) turns onnxruntime's worker-thread spinning on."""
    pytest.importorskip("onnx")
    import argparse

    from runtime_models import make_kinematic_model

    from prml2_edge.cli.runtime_app import build_pipeline, config_from_args
    from prml2_edge.cli.runtime_args import add_pipeline_arguments

    model = make_kinematic_model(tmp_path / "k.onnx")
    cfg = config_from_dict({"model": {"path": str(model), "threads": 2, "spinning": True},
                            "initial_pose": {"source": "config"}}, "cfg.toml")
    pipe = build_pipeline(cfg)
    opts = pipe.model.session.get_session_options()
    assert pipe.model.spinning and opts.get_session_config_entry("session.intra_op.allow_spinning") == "1"
    parser = argparse.ArgumentParser()
    add_pipeline_arguments(parser)
    args = parser.parse_args(["--model", str(model), "--spinning", "--initial-pose", "0,0,0"])
    assert config_from_args(args).model.spinning is True
    assert config_from_args(parser.parse_args([])).model.spinning is False


def test_gnss_section_and_the_flags_over_it(tmp_path):
    """[gnss] gives what --gnss, --gnss-origin and --gnss-time-offset give; a flag wins over the file, and each
    command reads its own key (run: receiver, replay: file), so one config serves both."""
    import argparse

    from prml2_edge.cli.runtime_app import config_from_args
    from prml2_edge.cli.runtime_args import add_gnss_arguments, add_pipeline_arguments

    p = tmp_path / "r.toml"
    p.write_text('[gnss]\nreceiver = "gpsd://box:2947"\nfile = "drive.nmea"\norigin = [48, 11.5]\n'
                 'time_offset_s = 3\n')

    def parsed(live: bool, *argv: str):
        parser = argparse.ArgumentParser()
        add_pipeline_arguments(parser)
        add_gnss_arguments(parser, live=live)
        return config_from_args(parser.parse_args(["--config", str(p), *argv])).gnss

    g = parsed(True)
    assert (g.receiver, g.file, g.origin, g.time_offset_s) == ("gpsd://box:2947", "drive.nmea", (48.0, 11.5), 3.0)
    g = parsed(True, "--gnss", "/dev/ttyACM0", "--gnss-origin", "47.5,9.25")
    assert (g.receiver, g.file, g.origin) == ("/dev/ttyACM0", "drive.nmea", (47.5, 9.25))
    g = parsed(False, "--gnss", "other.csv", "--gnss-time-offset", "-1.5")
    assert (g.receiver, g.file, g.origin, g.time_offset_s) == ("gpsd://box:2947", "other.csv", (48.0, 11.5), -1.5)
    assert RuntimeConfig().gnss.receiver is None and RuntimeConfig().gnss.time_offset_s == 0.0
    with pytest.raises(ConfigError, match="--gnss-origin must be LAT,LON"):
        parsed(True, "--gnss-origin", "48.1")
