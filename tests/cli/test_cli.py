"""The prml2 command line: help, one-line user errors, missing-extra hints."""

import subprocess
import sys

import pytest

from prml2_edge.cli.main import COMMANDS, main

BLOCK_TORCH = "import sys; sys.modules['torch'] = None; from prml2_edge.cli.main import main; sys.exit(main({argv!r}))"


def _run_blocked(argv):
    return subprocess.run([sys.executable, "-c", BLOCK_TORCH.format(argv=argv)], capture_output=True, text=True)


def test_help_lists_every_subcommand(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    for command in COMMANDS:
        assert command in out


@pytest.mark.parametrize("command", list(COMMANDS))
def test_each_subcommand_has_help(command, capsys):
    with pytest.raises(SystemExit) as exc:
        main([command, "--help"])
    assert exc.value.code == 0


def test_train_without_torch_prints_one_line_hint():
    proc = _run_blocked(["train", "--help"])
    assert proc.returncode == 1
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    assert "torch" in lines[0] and "[train]" in lines[0]
    assert "Traceback" not in proc.stderr


def test_help_works_without_torch():
    proc = _run_blocked(["--help"])
    assert proc.returncode == 0, proc.stderr
    assert "train" in proc.stdout


def test_unknown_subcommand_is_a_usage_error(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["no-such-command"])
    assert exc.value.code == 2
