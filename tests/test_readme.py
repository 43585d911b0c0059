"""The README's Quickstart holds exactly two commands, and .ci/run runs the second verbatim."""

import re


def _quickstart_commands(readme: str) -> list[str]:
    section = readme.split("## Quickstart", 1)[1].split("\n## ", 1)[0]
    blocks = re.findall(r"```bash\n(.*?)```", section, flags=re.S)
    cmds = [line for block in blocks for line in block.splitlines() if line.strip() and not line.startswith("#")]
    return cmds


def test_two_commands_and_ci_uses_the_second(repo_root):
    cmds = _quickstart_commands((repo_root / "README.md").read_text())
    assert len(cmds) == 2, cmds
    assert "prml2 demo" in cmds[0]
    assert "pytest" in cmds[1] and "ruff check" in cmds[1]
    ci = (repo_root / ".ci" / "run").read_text().splitlines()
    assert cmds[1] in ci
