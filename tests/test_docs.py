"""The README and docs/ point at files and sections that exist.

The measurements behind the defaults live in docs/measurements.md, the
main job's earlier numbers in docs/history.md; the README, the code's
comments and the benchmarks' docstrings refer to them by file and by
section title. These tests fail when a link, a record, a picture, a script
or a named section goes missing, so that a reference cannot rot silently.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md"] + sorted((ROOT / "docs").glob("*.md"))
MEASUREMENTS = ROOT / "docs" / "measurements.md"


def _flat(text: str) -> str:
    """Text with comment markers and line breaks folded into single spaces."""
    text = re.sub(r"^\s*(#:|#)\s?", "", text, flags=re.M)
    return re.sub(r"\s+", " ", text)


def _section_titles() -> list[str]:
    """Headings and bold or italic paragraph and bullet leads of docs/measurements.md."""
    text = MEASUREMENTS.read_text()
    heads = re.findall(r"^#+ (.+)$", text, re.M)
    leads = re.findall(r"^\s*(?:- )?\*{1,2}([^*]+?)\*", _flat_paragraphs(text), re.M)
    return [_flat(h).strip() for h in heads + leads]


def _flat_paragraphs(text: str) -> str:
    """One line per paragraph or bullet, so a bold lead that wraps is read whole."""
    return "\n".join(re.sub(r"\s*\n\s*", " ", p)
                     for p in re.split(r"\n\s*\n|\n(?=\s*- )", text))


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: p.name)
def test_links_resolve(doc):
    text = doc.read_text()
    missing = []
    for target in re.findall(r"\]\(([^)\s]+)\)", text):
        if re.match(r"[a-z]+://", target) or target.startswith("#"):
            continue
        path = (doc.parent / target.split("#")[0]).resolve()
        if not path.exists():
            missing.append(target)
    assert not missing, "%s links to missing files: %s" % (doc.name, missing)


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: p.name)
def test_named_records_pictures_and_scripts_exist(doc):
    text = doc.read_text()
    named = set(re.findall(r"`((?:docs/(?:bench|img)|tests/bench)/[\w.\-]+\.(?:json|png|py))", text))
    missing = sorted(p for p in named if not (ROOT / p).is_file())
    assert not missing, "%s names files that do not exist: %s" % (doc.name, missing)


def _section_references():
    """(where, title) for every reference to a section of docs/measurements.md."""
    refs = []
    sources = [ROOT / "README.md"] + sorted((ROOT / "mi_invrgbl").rglob("*.py")) \
        + sorted((ROOT / "tests" / "bench").glob("*.py"))
    for src in sources:
        text = _flat(src.read_text())
        rel = src.relative_to(ROOT)
        # 'docs/measurements.md, "Title"' (code) and '"Title" (docs/measurements.md)' (README)
        refs += [(rel, t) for t in re.findall(r'docs/measurements\.md,? "([^"]+)"', text)]
        refs += [(rel, t) for t in re.findall(r'"([^"]+)" (?:in )?\(?(?:\[)?docs/measurements\.md', text)]
        refs += [(rel, t) for t in re.findall(r'"([^"]+)" numbers in docs/measurements\.md', text)]
        refs += [(rel, t) for t in re.findall(r'"([^"]+)" table in docs/measurements\.md', text)]
    return refs


def test_section_references_name_a_section():
    refs = _section_references()
    assert len(refs) >= 20, "the reference patterns no longer match the sources (%d)" % len(refs)
    titles = _section_titles()
    unknown = ["%s: %r" % (where, t) for where, t in refs
               if not any(h.startswith(t.rstrip(".")) for h in titles)]
    assert not unknown, "references to no section of docs/measurements.md:\n" + "\n".join(unknown)
