"""The README stays short, its links and the docs site's links resolve, and the site builds."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
DOCS = ROOT / "docs"
PAGES = [README, *sorted(DOCS.rglob("*.md"))]

_LINK = re.compile(r"\[[^\]]*\]\(([^)\s]+)\)")
_FENCE = re.compile(r"^(```|~~~)")


def _prose(text: str) -> str:
    """The text outside fenced and indented code blocks, where a link is a link."""
    out, fence = [], False
    for line in text.splitlines():
        if _FENCE.match(line):
            fence = not fence
            continue
        if fence or line.startswith("    "):
            continue
        out.append(re.sub(r"`[^`]*`", "", line))  # inline code holds no links
    return "\n".join(out)


def _anchors(path: Path) -> set[str]:
    """Heading slugs (MkDocs' and GitHub's) and explicit ids of a Markdown file."""
    try:
        from markdown.extensions.toc import slugify  # MkDocs' own slugs
    except ImportError:  # markdown comes with mkdocs (the test extra); GitHub's slugs alone
        def slugify(value, separator):
            return re.sub(r"[^\w\- ]", "", value.lower()).strip().replace(" ", separator)

    found, fence = set(), False
    for line in path.read_text().splitlines():
        if _FENCE.match(line):
            fence = not fence
            continue
        if fence:
            continue
        found.update(re.findall(r'id="([^"]+)"', line))
        heading = re.match(r"^#{1,6}\s+(.*?)\s*#*\s*$", line)
        if heading:
            title = heading.group(1)
            found.add(slugify(title.replace("`", ""), "-"))
            github = re.sub(r"[^\w\- ]", "", title.lower()).replace(" ", "-")
            found.add(github)
    return found


def _relative_links(page: Path) -> list[str]:
    return [target for target in _LINK.findall(_prose(page.read_text()))
            if not re.match(r"^[a-z][a-z0-9+.-]*:", target)]  # http:, mailto:, ...


def test_readme_is_at_most_400_lines():
    lines = README.read_text().count("\n")
    assert lines <= 400, f"README.md has {lines} lines; move detail into docs/"


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_relative_link_points_to_an_existing_file_and_anchor(page):
    broken = []
    for target in _relative_links(page):
        path_part, _, anchor = target.partition("#")
        dest = (page.parent / path_part).resolve() if path_part else page
        if not dest.exists():
            broken.append(f"{target}: no file {dest.relative_to(ROOT) if dest.is_relative_to(ROOT) else dest}")
        elif anchor and dest.suffix == ".md" and anchor not in _anchors(dest):
            broken.append(f"{target}: no heading or id '{anchor}' in {dest.name}")
    assert not broken, f"{page.relative_to(ROOT)}: " + "; ".join(broken)


def test_the_link_checker_finds_a_broken_file_and_a_broken_anchor(tmp_path):
    page = tmp_path / "page.md"
    (tmp_path / "other.md").write_text("# A title\n\n<a id=\"kept\"></a>\n")
    page.write_text("[ok](other.md#a-title) [ok](other.md#kept) [bad](missing.md) [bad](other.md#nope)\n"
                    "    [code](not-a-link.md)\n")
    links = _relative_links(page)
    assert links == ["other.md#a-title", "other.md#kept", "missing.md", "other.md#nope"]
    assert {"a-title", "kept"} <= _anchors(tmp_path / "other.md")
    assert "nope" not in _anchors(tmp_path / "other.md")


def test_every_docs_page_is_in_the_nav():
    nav = (ROOT / "mkdocs.yml").read_text()
    missing = [str(p.relative_to(DOCS)) for p in DOCS.rglob("*.md") if str(p.relative_to(DOCS)) not in nav]
    assert not missing, f"pages not in mkdocs.yml's nav: {missing}"


def test_the_docs_site_builds_strict_with_the_api_reference(tmp_path):
    pytest.importorskip("mkdocs")
    pytest.importorskip("mkdocstrings_handlers.python")
    site = tmp_path / "site"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    done = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--quiet", "-f",
                           str(ROOT / "mkdocs.yml"), "-d", str(site)],
                          cwd=ROOT, env=env, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-3000:]
    api = (site / "api" / "index.html").read_text()
    for name in ("calibrate", "fit", "Session", "read_tracks", "InputError"):  # docstrings rendered
        assert f'id="mocap.api.{name}"' in api, name
    assert (site / "commands" / "reconstruct" / "index.html").exists()
    assert (site / "benchmarks" / "tracking" / "index.html").exists()
