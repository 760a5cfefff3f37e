"""MkDocs hook: the repository's ``reports/`` published in the site.

The pages under ``docs/`` cite results by relative links (``../reports/loop_cases.md``)
that work on GitHub and in an editor. In the built site those files would be
outside it; this hook adds every report (Markdown, figures, JSON) to the site
under ``reports/`` and rewrites the pages' ``../reports/`` links to it, so the
links of the built site lead to the reports too. Named in ``mkdocs.yml``'s
``hooks``.
"""

from __future__ import annotations

from pathlib import Path

from mkdocs.structure.files import File, Files

REPORTS = Path(__file__).resolve().parents[1] / "reports"
#: What a report links to: its text, its figures, its data.
PUBLISHED = {".md", ".png", ".svg", ".json"}


def on_files(files: Files, config) -> Files:
    for path in sorted(REPORTS.rglob("*")):
        if path.is_file() and path.suffix in PUBLISHED:
            uri = "reports/" + path.relative_to(REPORTS).as_posix()
            files.append(File.generated(config, uri, abs_src_path=str(path)))
    return files


def on_page_markdown(markdown: str, page, config, files) -> str:
    if page.file.src_uri.startswith("reports/"):
        return markdown  # a report's own links are relative to reports/ already
    return markdown.replace("](../reports/", "](reports/")
