"""The README: a short front page whose Quickstart holds exactly two commands, the second run verbatim by .ci/run."""

import re

README_MAX_BYTES = 12 * 1024


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
    # the docs site is built strictly (every broken link or anchor fails) with the docs extra
    assert "mkdocs build --strict" in cmds[1] and "docs]" in cmds[1]
    ci = (repo_root / ".ci" / "run").read_text().splitlines()
    assert cmds[1] in ci


def test_the_docs_front_page_has_the_same_quickstart(repo_root):
    readme = _quickstart_commands((repo_root / "README.md").read_text())
    docs = _quickstart_commands((repo_root / "docs" / "index.md").read_text())
    assert docs == readme


def test_readme_is_a_front_page(repo_root):
    size = len((repo_root / "README.md").read_bytes())
    assert size <= README_MAX_BYTES, f"README.md is {size} bytes; the rest belongs in docs/"


def test_readme_links_to_bring_your_own_car(repo_root):
    readme = (repo_root / "README.md").read_text()
    assert "](docs/bring-your-own-car.md)" in readme
    assert (repo_root / "docs" / "bring-your-own-car.md").is_file()
