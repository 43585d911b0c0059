"""The docs site (mkdocs.yml, docs/): every page in the nav, every prml2 command documented, tables re-rendered
from benchmark JSON with the commit and command that produced them."""

from __future__ import annotations

import argparse
import importlib.util
import json
import re
from pathlib import Path

from prml2_edge.cli.main import build_parser


def _nav_pages(repo_root: Path) -> list[str]:
    """The .md files of mkdocs.yml's nav (read as text: the file has a !!python/name tag safe_load refuses)."""
    text = (repo_root / "mkdocs.yml").read_text()
    nav = text.split("\nnav:\n", 1)[1]
    nav = re.split(r"\n(?=\S)", nav, maxsplit=1)[0]  # up to the next top-level key
    return re.findall(r"^\s*-\s*(?:[^:\n]+:\s*)?([\w/.-]+\.md)\s*$", nav, flags=re.M)


def _subcommands() -> list[str]:
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return list(sub.choices)


def test_every_page_is_in_the_nav_and_exists(repo_root):
    nav = _nav_pages(repo_root)
    assert "index.md" in nav and "bring-your-own-car.md" in nav and "commands.md" in nav
    on_disk = {p.relative_to(repo_root / "docs").as_posix() for p in (repo_root / "docs").rglob("*.md")}
    assert set(nav) == on_disk
    assert len(nav) == len(set(nav))


def test_every_subcommand_is_documented_in_the_nav(repo_root):
    commands = _subcommands()
    assert "demo" in commands and "doctor" in commands  # the parser was read, not an empty list
    pages = {p: (repo_root / "docs" / p).read_text() for p in _nav_pages(repo_root)}
    for name in commands:
        used = [p for p, text in pages.items() if p != "commands.md" and f"prml2 {name}" in text]
        assert used, f"prml2 {name} appears in no docs page besides the commands page"
    # the commands page: one row per subcommand, each linking to a page of the site
    rows = {}
    for line in pages["commands.md"].splitlines():
        m = re.match(r"\| `prml2 (\w+)[^`]*` \|", line)
        if m:
            rows.setdefault(m.group(1), []).append(line)
    assert set(commands) <= set(rows), set(commands) - set(rows)
    for name in commands:
        links = [target.split("#")[0] for line in rows[name] for target in re.findall(r"\]\(([^)]+)\)", line)]
        assert links and all(t in pages for t in links), (name, links)


def test_byoc_is_within_two_clicks_and_uses_real_flags(repo_root):
    page = (repo_root / "docs" / "bring-your-own-car.md").read_text()
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    for command, flags in (("doctor", ("--log", "--map", "--dbc")), ("replay", ("--mcap", "--gnss", "--truth")),
                           ("run", ("--interface", "--channel", "--gnss")), ("encode", ("--map", "--gnss-seconds"))):
        assert f"prml2 {command}" in page
        known = {s for a in sub.choices[command]._actions for s in a.option_strings}
        for flag in flags:
            assert flag in known and flag in page, (command, flag)


def _render_tables(repo_root: Path):
    spec = importlib.util.spec_from_file_location("render_tables", repo_root / "benchmarks" / "render_tables.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_render_tables_from_json_with_commit_and_command(repo_root, tmp_path):
    rt = _render_tables(repo_root)
    results, docs = tmp_path / "results", tmp_path / "docs"
    results.mkdir()
    docs.mkdir()
    (results / "fuzz.json").write_text(json.dumps({
        "machine": {"commit": "abc1234", "command": "python benchmarks/fuzz.py --frames 1000"},
        "frames": 1000, "received": 1000, "used": 600, "ignored": 150, "rejected": 250, "balanced": True,
        "nonfinite_poses": 0, "exception": None, "wall_s": 0.5}))
    page = docs / "reliability.md"
    page.write_text("# Fuzz\n\nbefore\n\n<!-- results:fuzz -->\nan old table\n<!-- /results -->\n\nafter\n\n"
                    "<!-- results:soak -->\nhand-written, no JSON\n<!-- /results -->\n")
    assert rt.main(["--docs", str(docs), "--results", str(results), "--check"]) == 1
    assert rt.render(docs, results) == [page]
    text = page.read_text()
    assert "an old table" not in text
    assert "| 1 000 | 600 | 150 | 250 | yes | 0 | nothing | 0.5 |" in text
    source = f"Source: `python benchmarks/fuzz.py --frames 1000` at commit `abc1234`, `{results.resolve()}/fuzz.json`."
    assert source in text
    assert text.startswith("# Fuzz\n\nbefore\n\n<!-- results:fuzz -->\n") and "-->\n\nafter\n\n" in text
    assert "<!-- results:soak -->\nhand-written, no JSON\n<!-- /results -->" in text  # no JSON: kept as it was
    assert rt.render(docs, results) == []  # idempotent
    assert rt.main(["--docs", str(docs), "--results", str(results), "--check"]) == 0


def test_the_shipped_docs_blocks_all_have_a_renderer_and_a_source_line(repo_root):
    rt = _render_tables(repo_root)
    for page in (repo_root / "docs").rglob("*.md"):
        for m in rt.BLOCK.finditer(page.read_text()):
            assert m.group(2) in rt.RENDERERS, (page.name, m.group(2))
            assert "Source: " in m.group(3) and "commit `" in m.group(3), (page.name, m.group(2))


def test_benchmark_json_says_which_commit_and_command(monkeypatch, repo_root):
    from prml2_edge.bench import machine

    monkeypatch.setattr("sys.argv", [str(repo_root / "benchmarks" / "fuzz.py"), "--frames", "10"])
    p = machine.provenance()
    assert p["command"] == "python benchmarks/fuzz.py --frames 10"
    assert p["commit"] is None or re.fullmatch(r"[0-9a-f]{4,40}(\+dirty)?", p["commit"])
