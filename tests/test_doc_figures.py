"""Every measured figure a guide quotes is on a generated results page, linked beside it.

A guide quotes a measurement as a link whose text is the figure and whose target is the
section of the results page that holds it, e.g. ``[0.025 mm](results/accuracy.md#demo)``;
tools/gen_results.py marks every section with such an anchor (``<a id="NAME"></a>``: the
demo, and each benchmark by its name). Two checks:

1. every number in such a link's text is in that section (rounded to the digits the guide
   quotes), outside the run's date and machine lines: a guide cannot keep a figure that the
   page it cites does not have, and a regenerated page that moved a figure breaks the guide;
2. a paragraph (with the table it introduces) that says a figure was measured (measured,
   took, came out, gave, ...) quotes no figure with a unit outside such links and outside
   code: a hand-run measurement cannot enter a guide unlinked. Design values, tolerances and
   specifications are written without those words, or in code.

docs/reference.md (generated from the code) and the results pages themselves are not guides.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
GUIDES = [ROOT / 'README.md', *sorted(p for p in (ROOT / 'docs').rglob('*.md')
                                      if p.name != 'reference.md' and 'results' not in p.parts)]

#: a link whose text holds a digit and whose target is a section of a results page
FIGURE_LINK = re.compile(r'\[([^\]]*\d[^\]]*)\]\(([^)\s#]*results/[\w-]+\.md)#([\w-]+)\)')
#: a number as written: thousands grouped with commas (10,000), decimals, a sign
NUMBER = re.compile(r'(?<![\w.])([-+−]?)(\d{1,3}(?:,\d{3})+|\d+)(\.\d+)?(?![\d])')
#: words that say a figure was measured
MEASURED = re.compile(r'\b(measured|took|came out|comes out|gave)\b', re.I)
#: how far from the words that say so a measured figure is looked for [characters]
NEAR = 80
#: where a sentence ends
SENTENCE_END = re.compile(r'(?<=[.;!?])\s+(?=[A-Z(*`\[])|\n(?=\s*(?:[-*]|\d+\.)\s)')
#: a figure with a unit of the quantities galvoscan measures
FIGURE = re.compile(r'(?<![\w.])\d+(?:\.\d+)?\s?(?:mm|µm|um|px|ms|µs|us|s|min|%|Hz|mrad|deg|°|x)'
                    r'(?![\w])')
#: lines of a results section that hold the run's circumstances, not its figures
PROVENANCE = re.compile(r'^- (command|date|machine):', re.M)


def _numbers(text: str) -> list[tuple[float, int]]:
    """(value, decimals) of every number written in ``text``."""
    out = []
    for sign, whole, frac in NUMBER.findall(text):
        value = float(whole.replace(',', '') + (frac or ''))
        out.append((-value if sign in '-−' and sign else value, len(frac) - 1 if frac else 0))
    return out


def _section(page: Path, anchor: str) -> str | None:
    text = page.read_text()
    start = text.find(f'<a id="{anchor}"></a>')
    if start < 0:
        return None
    end = text.find('<a id="', start + 1)
    section = text[start:end if end > 0 else None]
    return '\n'.join(line for line in section.splitlines() if not PROVENANCE.match(line))


def _prose(text: str) -> str:
    """``text`` without code: fenced and indented blocks, inline code."""
    text = re.sub(r'^```.*?^```', '', text, flags=re.M | re.S)
    text = re.sub(r'(?m)^(?: {4}|\t).*$', '', text)
    return re.sub(r'`[^`]*`', '', text)


def figure_links():
    for guide in GUIDES:
        text = _prose(guide.read_text())
        for m in FIGURE_LINK.finditer(text):
            line = text.count('\n', 0, m.start()) + 1
            yield pytest.param(guide, m.group(1), m.group(2), m.group(3),
                               id=f'{guide.relative_to(ROOT)}:{line}:{m.group(3)}')


def test_guides_quote_figures_from_the_results_pages():
    assert len(list(figure_links())) >= 10


@pytest.mark.parametrize(('guide', 'figure', 'page', 'anchor'), list(figure_links()))
def test_a_quoted_figure_is_on_the_page_it_links(guide, figure, page, anchor):
    target = (guide.parent / page).resolve()
    assert target.is_file(), f'{figure!r} links to {page}, which does not exist'
    section = _section(target, anchor)
    assert section is not None, f'{figure!r}: {page} has no section #{anchor}'
    on_page = [v for v, _ in _numbers(section)]
    for value, decimals in _numbers(figure):
        tolerance = 0.5 * 10 ** -decimals + 1e-9
        assert any(abs(x - value) <= tolerance for x in on_page), (
            f'{guide.relative_to(ROOT)} quotes {figure!r}, but {page}#{anchor} has no '
            f'{value:g} (to {decimals} decimals): take the figure from the page, or '
            f'regenerate the page (tools/gen_results.py)')


def test_every_link_into_a_results_page_finds_its_section():
    link = re.compile(r'\]\(([^)\s#]*results/[\w-]+\.md)#([\w-]+)\)')
    missing = []
    for guide in GUIDES:
        for page, anchor in link.findall(_prose(guide.read_text())):
            target = (guide.parent / page).resolve()
            if not target.is_file() or _section(target, anchor) is None:
                missing.append(f'{guide.relative_to(ROOT)}: {page}#{anchor}')
    assert not missing, 'links to no results section:\n' + '\n'.join(missing)


def unlinked_measurements(text: str) -> list[str]:
    """Sentences that say a figure was measured and quote one with a unit, outside a results
    link, within :data:`NEAR` characters of the saying, or in the table the sentence
    introduces."""
    text = FIGURE_LINK.sub('', _prose(text))
    sentences = []  # (sentence, the table it introduces)
    for block in re.split(r'\n\s*\n', text):
        if block.lstrip().startswith('|') and sentences:
            sentences[-1] = (sentences[-1][0], sentences[-1][1] + '\n' + block)
        else:
            sentences += [(s, '') for s in SENTENCE_END.split(block)]
    bad = []
    for sentence, table in sentences:
        for m in MEASURED.finditer(sentence):
            near = sentence[max(0, m.start() - NEAR):m.end() + NEAR]
            if FIGURE.search(near) or FIGURE.search(table):
                bad.append(' '.join(sentence.split())[:300])
                break
    return bad


def test_the_check_finds_an_unlinked_measurement():
    assert unlinked_measurements('The stair came out at 0.025 mm on the reference rig.')
    assert unlinked_measurements('Measured:\n\n| figure | value |\n|---|---|\n| x | 3.1 us |')
    assert not unlinked_measurements(
        'The stair came out at [0.025 mm](results/accuracy.md#demo) on the reference rig.')
    assert not unlinked_measurements('The sphere must be within 4 mm of the place asked for.')
    assert not unlinked_measurements('It measured `--frames 5` frames.')
    assert unlinked_measurements('20,000 frames (25 s of board time) gave 0 crashes.')


@pytest.mark.parametrize('guide', GUIDES, ids=lambda p: str(p.relative_to(ROOT)))
def test_no_guide_quotes_a_measurement_without_its_results_page(guide):
    bad = unlinked_measurements(guide.read_text())
    assert not bad, (
        f'{guide.relative_to(ROOT)} quotes measured figures that no results page links; '
        'add the benchmark to tools/gen_results.py and link its section as '
        '[figure](results/PAGE.md#NAME), or drop the figure:\n' + '\n'.join(bad))
