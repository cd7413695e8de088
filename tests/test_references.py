"""Every place the code cites one of the four papers by equation, section, figure, table or
appendix, it names the arXiv version the number refers to (``jaxdrive.references``)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from jaxdrive.references import PAPERS, paper

ROOT = Path(__file__).resolve().parents[1]
NAMES = "|".join(re.escape(n) for n in PAPERS)
# "MiLA eq. 13", "MiLA's eq. 13", "MagicDrive-V2 appendix B", "STAGE sec. 3.2", ... : a numbered place
PLACE = r"(?:eqs?\.|equations?|secs?\.|sections?|§|figs?\.|figures?|tables?|appendix|app\.)\s*\(?[0-9A-Z]"
CITED = re.compile(rf"\b({NAMES})(?:'s)?(\s+\[[^\]]*\])?\s+{PLACE}")


def citations(text: str):
    return [(m.group(1), m.group(2), m.group(0)) for m in CITED.finditer(text)]


def test_the_pattern_finds_bare_and_versioned_citations():
    found = citations("MiLA eq. 13; LongDWM [2506.01546v1] eq. 4, MagicDrive-V2 appendix B and STAGE's table 2")
    assert [(name, bool(tag)) for name, tag, _ in found] == [
        ("MiLA", False),
        ("LongDWM", True),
        ("MagicDrive-V2", False),
        ("STAGE", False),
    ]
    assert citations("MiLA drops text (not a numbered place)") == []


def test_every_numbered_citation_of_a_paper_names_its_arxiv_version():
    bad = []
    for path in sorted([*(ROOT / "jaxdrive").rglob("*.py"), *(ROOT / "configs").rglob("*.py")]):
        for name, tag, text in citations(path.read_text()):
            if tag is None or tag.strip()[1:-1] != PAPERS[name].arxiv:
                bad.append(f"{path.relative_to(ROOT)}: {text!r} (expected {PAPERS[name].cite()})")
    assert not bad, "\n".join(bad)


def test_papers_carry_a_versioned_arxiv_id_and_reject_unknown_names():
    assert {p.name for p in PAPERS.values()} == {"MiLA", "LongDWM", "STAGE", "MagicDrive-V2"}
    for p in PAPERS.values():
        assert re.fullmatch(r"\d{4}\.\d{5}v\d+", p.arxiv) and p.url.endswith(p.arxiv)
    assert paper("MiLA").cite("eq. 13") == "MiLA [2503.15875v1] eq. 13"
    with pytest.raises(ValueError, match="name: expected one of MiLA, LongDWM, STAGE, MagicDrive-V2, got 'Vista'"):
        paper("Vista")
