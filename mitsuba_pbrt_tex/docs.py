"""Parameter tables read from the plugins' docstrings (the single source for ``info`` and README).

Each plugin module's docstring contains one Markdown table with the columns
``parameter | type | default | meaning | differentiable``. A row whose parameter cell is
``(2D mapping)`` or ``(3D mapping)`` stands for the mapping parameters, which are documented once
in :mod:`mitsuba_pbrt_tex.mapping` and expanded here.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass

from .registry import PLUGINS, plugin_module

COLUMNS = ('parameter', 'type', 'default', 'meaning', 'differentiable')
MAPPING_ROWS = {'(2D mapping)': 0, '(3D mapping)': 1}


@dataclass
class Row:
    parameter: str
    type: str
    default: str
    meaning: str
    differentiable: str

    def names(self) -> list[str]:
        """Parameter names in the cell (``uscale, vscale`` → two names)."""
        return [n.strip() for n in self.parameter.split(',') if n.strip()]


def _split(line: str) -> list[str]:
    cells = line.strip().strip('|').split('|')
    return [c.strip() for c in cells]


def tables(doc: str) -> list[list[Row]]:
    """All parameter tables in a docstring, in order."""
    out, current = [], None
    for line in (doc or '').splitlines():
        s = line.strip()
        if s.startswith('|') and s.endswith('|'):
            cells = _split(s)
            if current is None:
                if tuple(c.lower() for c in cells) == COLUMNS:
                    current = []
                continue
            if all(set(c) <= set('-: ') for c in cells):
                continue
            if len(cells) != len(COLUMNS):
                raise ValueError(f'malformed parameter-table row: {line!r}')
            current.append(Row(*cells))
        elif current is not None:
            out.append(current)
            current = None
    if current is not None:
        out.append(current)
    return out


def mapping_rows(which: int) -> list[Row]:
    mapping = importlib.import_module('mitsuba_pbrt_tex.mapping')
    return tables(mapping.__doc__)[which]


def plugin_rows(name: str, expand: bool = True) -> list[Row]:
    """The parameter table of plugin ``name`` (mapping rows expanded by default)."""
    found = tables(plugin_module(name).__doc__)
    if not found:
        raise ValueError(f'plugin {name} has no parameter table in its docstring')
    rows = []
    for row in found[0]:
        if expand and row.parameter in MAPPING_ROWS:
            rows.extend(mapping_rows(MAPPING_ROWS[row.parameter]))
        else:
            rows.append(row)
    return rows


def summary(name: str) -> str:
    """The first docstring line of plugin ``name`` (without the name)."""
    first = (plugin_module(name).__doc__ or '').strip().splitlines()[0]
    return first.split('—', 1)[-1].strip()


def markdown(names=PLUGINS) -> str:
    """The README's plugin reference: one section and table per plugin."""
    parts, mappings = [], set()
    for name in names:
        parts.append(f'### `{name}`\n\n{summary(name)}\n')
        parts.append('| ' + ' | '.join(COLUMNS) + ' |')
        parts.append('|' + '---|' * len(COLUMNS))
        for r in plugin_rows(name, expand=False):
            if r.parameter in MAPPING_ROWS:
                mappings.add(MAPPING_ROWS[r.parameter])
                r = Row(r.parameter, '', '', 'see [Mappings](#mappings)', '')
            parts.append(f'| {r.parameter} | {r.type} | {r.default} | {r.meaning} | {r.differentiable} |')
        parts.append('')
    if mappings:                        # (only the tables these plugins refer to)
        parts.append('### Mappings\n')
    for title, which in (('2D mapping parameters', 0), ('3D mapping parameters', 1)):
        if which not in mappings:
            continue
        parts.append(f'{title}:\n')
        parts.append('| ' + ' | '.join(COLUMNS) + ' |')
        parts.append('|' + '---|' * len(COLUMNS))
        for r in mapping_rows(which):
            parts.append(f'| {r.parameter} | {r.type} | {r.default} | {r.meaning} | {r.differentiable} |')
        parts.append('')
    return '\n'.join(parts).rstrip() + '\n'


def text(names=PLUGINS) -> str:
    """Plain-text listing for ``python -m mitsuba_pbrt_tex info``."""
    lines = []
    for name in names:
        lines.append(f'{name}: {summary(name)}')
        rows = plugin_rows(name)
        width = max((len(r.parameter) for r in rows), default=0)
        for r in rows:
            diff = ' [differentiable]' if r.differentiable.lower().startswith('yes') else ''
            default = f' (default: {r.default})' if r.default and r.default != '—' else ''
            lines.append(f'  {r.parameter:<{width}}  {r.type}{default}{diff}')
            lines.append(f'  {"":<{width}}    {r.meaning}')
        lines.append('')
    return '\n'.join(lines)


PLUGIN_MARKERS = ('<!-- BEGIN PLUGIN REFERENCE -->', '<!-- END PLUGIN REFERENCE -->')
BENCH_MARKERS = ('<!-- BEGIN BENCH SUMMARY -->', '<!-- END BENCH SUMMARY -->')


def _replace_section(text: str, markers: tuple[str, str], body: str, path: str) -> str:
    import re
    pattern = re.escape(markers[0]) + '.*?' + re.escape(markers[1])
    if len(re.findall(pattern, text, flags=re.S)) != 1:
        raise ValueError(f'"{path}" has no section between the lines {markers[0]} and '
                         f'{markers[1]} (or more than one); add them where the section belongs; '
                         f'nothing was changed')
    return re.sub(pattern, lambda m: markers[0] + '\n' + body + markers[1], text, flags=re.S)


#: How the results.md of ``bench render --quick`` begins.
QUICK_MARK = 'Smoke test (--quick'


def _summary_scenes(summary: str) -> set:
    """The scenes a benchmark summary has lines for (``- **scene**…``)."""
    import re
    return set(re.findall(r'^- \*\*([^*]+)\*\*', summary, flags=re.M))


def _bench_summary(bench_results: str, readme: str) -> str:
    """The summary of ``bench_results`` (a ``bench render`` results.md) for the README, or
    ValueError where it is not a full run's: no summary, a ``--quick`` smoke test, or fewer
    scenes than the README's summary has (a ``--scenes`` subset; splice it into the full
    report first)."""
    text = open(bench_results, encoding='utf-8').read()
    parts = text.split('## Summary')
    if len(parts) < 2:
        raise ValueError(f'"{bench_results}" has no "## Summary" section (expected the '
                         f'results.md of a full `bench render` run); nothing was changed')
    if text.startswith(QUICK_MARK):
        raise ValueError(f'"{bench_results}" is from `bench render --quick` (a smoke test, not a '
                         f'measurement); nothing was changed')
    summary = parts[1].strip()
    import re
    old = re.findall(re.escape(BENCH_MARKERS[0]) + '(.*?)' + re.escape(BENCH_MARKERS[1]),
                     readme, flags=re.S)
    missing = _summary_scenes(old[0]) - _summary_scenes(summary) if len(old) == 1 else set()
    if missing == {'matpreview-photo'} and 'envlit-photo' in _summary_scenes(summary):
        raise ValueError(f'"{bench_results}" is from a run without --mitsuba-data (its '
                         f'real-scene case is the look-alike envlit-photo, the README\'s is '
                         f'matpreview-photo): run `bench render --mitsuba-data DIR`; nothing was '
                         f'changed')
    if missing:
        raise ValueError(f'"{bench_results}" has no summary of {", ".join(sorted(missing))}, '
                         f'which the README has (a run of some scenes: splice its rows into '
                         f'the full report first); nothing was changed')
    return summary


def update_readme(path: str, bench_results: str | None = None) -> bool:
    """Rewrite README's generated sections: the plugin reference and (given the benchmark's
    ``results.md``) its summary lines. Raises ValueError (changing nothing) if a section's
    markers are missing; returns whether the file changed."""
    text = open(path, encoding='utf-8').read()
    new = _replace_section(text, PLUGIN_MARKERS, markdown(), path)
    if bench_results:
        new = _replace_section(new, BENCH_MARKERS, _bench_summary(bench_results, new) + '\n',
                               path)
    if new == text:
        return False
    with open(path, 'w', encoding='utf-8') as f:
        f.write(new)
    return True
