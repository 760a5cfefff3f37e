"""The documents in ``docs/`` and the README: their links lead somewhere,
and the documentation site builds."""

from __future__ import annotations

import importlib.util
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
LINK = re.compile(r"\]\(([^)#\s]*)(?:#([^)\s]*))?\)")
FENCE = re.compile(r"^\s*(```|~~~)")
#: A commit hash as a word: 7-40 hex digits, at least one letter and one digit.
COMMIT = re.compile(r"\b(?=[0-9a-f]*[a-f])(?=[0-9a-f]*[0-9])[0-9a-f]{7,40}\b")
#: A wall time: a figure followed by s, min, ms or h ("48 s", "1.1 s", "27 min").
WALL_TIME = re.compile(r"\b\d+(?:\.\d+)? ?(?:s|min|ms|h)\b")


def heading_slugs(text: str) -> set[str]:
    """The anchors of a Markdown page's headings, as GitHub and MkDocs make them.

    Lower case, markup and punctuation other than ``-`` and ``_`` dropped, each
    space a ``-``; a repeated heading gets ``-1``, ``-2``, ... Headings inside
    fenced code blocks are not headings.
    """
    slugs: set[str] = set()
    in_code = False
    for line in text.splitlines():
        if FENCE.match(line):
            in_code = not in_code
            continue
        match = None if in_code else re.match(r"^#{1,6}\s+(.*?)\s*#*\s*$", line)
        if match is None:
            continue
        # a link in a heading counts as its text
        title = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", match.group(1))
        slug = re.sub(r"[^\w\- ]", "", title.strip().lower()).replace(" ", "-")
        unique, n = slug, 0
        while unique in slugs:
            n += 1
            unique = f"{slug}-{n}"
        slugs.add(unique)
    return slugs


def test_the_heading_slugs_follow_github():
    text = "# Training\n## Errors and exit codes\n```bash\n# a comment\n```\n"
    text += "## Errors\n## Errors\n"
    text += "### Sequential refinement (SMC)\n## What the loop `finds`: [here](x.md)\n"
    assert heading_slugs(text) == {
        "training",
        "errors-and-exit-codes",
        "errors",
        "errors-1",
        "sequential-refinement-smc",
        "what-the-loop-finds-here",
    }


def test_the_docs_links_lead_to_files_of_the_project():
    """Every relative Markdown link of README.md and docs/*.md names a file.

    A link's ``#anchor`` into a Markdown file (or into its own page) must name
    one of that file's headings.
    """
    checked = anchors = 0
    for page in PAGES:
        for target, anchor in LINK.findall(page.read_text()):
            if "://" in target or target.startswith("mailto:"):
                continue
            path = (page.parent / target) if target else page
            assert path.exists(), f"{page.name}: {target}"
            checked += 1
            if anchor and path.suffix == ".md":
                assert anchor in heading_slugs(path.read_text()), (
                    f"{page.name}: {target}#{anchor} names no heading of {path.name}"
                )
                anchors += 1
    assert checked >= 2  # the README's links to docs/ at least
    assert anchors >= 1


def test_the_docs_home_shows_the_readme_set_up_lines():
    """docs/index.md repeats the README's two set-up lines exactly: the first
    code block, on the README's first screen (its first 25 lines)."""
    readme = (ROOT / "README.md").read_text().splitlines()
    first = readme.index("```bash") + 1
    assert first < 25
    setup = readme[first : first + 2]
    assert all(line.startswith("python3 -m venv") for line in setup)
    assert readme[first + 2] == "```"
    index = (ROOT / "docs" / "index.md").read_text().splitlines()
    start = index.index(setup[0])
    assert index[start + 1] == setup[1]


def test_the_docs_site_builds_strict(tmp_path):
    """``mkdocs build --strict`` passes; only links that leave docs/ are not pages."""
    if importlib.util.find_spec("mkdocs") is None:
        pytest.skip("mkdocs is not installed (it is in the dev extra)")
    site = tmp_path / "site"
    proc = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(site)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=600,
    )
    output = proc.stdout + proc.stderr
    assert proc.returncode == 0, output
    assert (site / "index.html").exists(), output
    # mkdocs.yml reports links "not found among documentation files" as info, for
    # the links to ../reports/ and the like; a link that stays inside docs/ and
    # is not found is a broken page link.
    docs = (ROOT / "docs").resolve()
    told = re.findall(r"Doc file '([^']+)' contains a link '([^']+)'", output)
    for page, link in told:
        target = ((docs / page).parent / link.split("#", 1)[0]).resolve()
        assert not target.is_relative_to(docs), f"{page}: broken link {link}\n{output}"
        assert "reports/" not in link, f"{page}: {link} leads nowhere in the site"
    # the API reference is generated from the docstrings (mkdocstrings)
    public = (site / "api" / "public" / "index.html").read_text()
    for name in ("load_pairs", "simulate", "HybridSampler", "get_model"):
        assert f'id="torchcf.{name}"' in public, name
    # the reports the pages cite are published beside them (tools/docs_reports.py)
    assert (site / "reports" / "loop_cases" / "index.html").exists()
    loop = (site / "loop" / "index.html").read_text()
    assert 'href="../reports/loop_heterogeneous/"' in loop


def pinned_data_commit() -> str:
    """The commit of the authors' data repository that torchcf downloads from."""
    from torchcf.data.registry import SOURCE_URL

    match = re.search(r"/([0-9a-f]{40})/", SOURCE_URL)
    assert match is not None, SOURCE_URL
    return match.group(1)


def test_the_commit_hash_pattern():
    text = "at 7bb6e03, e4d4982 and 64a2872a7dc9; not 1000000, deadbeef, 0x1f or abc12"
    assert COMMIT.findall(text) == ["7bb6e03", "e4d4982", "64a2872a7dc9"]


def test_the_docs_name_no_commit():
    """Commit hashes date measurements, and those live in ``reports/``: no page
    of docs/ nor the README names one. The exception is a fact about the code:
    docs/data.md names the commit of the authors' data repository that
    ``torchcf.data.registry`` downloads from (a prefix of 7 or more digits)."""
    pinned = pinned_data_commit()
    found = []
    for page in PAGES:
        for word in COMMIT.findall(page.read_text()):
            if page.name == "data.md" and pinned.startswith(word):
                continue
            found.append(f"{page.relative_to(ROOT)}: {word}")
    assert not found, "commit hashes belong in reports/: " + ", ".join(found)
    data_page = (ROOT / "docs" / "data.md").read_text()
    assert any(pinned.startswith(word) for word in COMMIT.findall(data_page)), (
        "docs/data.md no longer names the data commit the code downloads from"
    )


def test_the_performance_page_quotes_no_wall_time():
    """docs/performance.md describes how the code is made fast; the seconds,
    per machine and revision, are in reports/performance.md."""
    assert WALL_TIME.findall(
        "took 48 s, 1.1 s a chunk, 27 min; 2^16 cells, 8 steps"
    ) == [
        "48 s",
        "1.1 s",
        "27 min",
    ]
    text = (ROOT / "docs" / "performance.md").read_text()
    assert WALL_TIME.findall(text) == [], "wall times belong in reports/performance.md"
    assert (ROOT / "reports" / "performance.md").exists()
