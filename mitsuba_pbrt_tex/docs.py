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
    parts = []
    for name in names:
        parts.append(f'### `{name}`\n\n{summary(name)}\n')
        parts.append('| ' + ' | '.join(COLUMNS) + ' |')
        parts.append('|' + '---|' * len(COLUMNS))
        for r in plugin_rows(name, expand=False):
            if r.parameter in MAPPING_ROWS:
                r = Row(r.parameter, '', '', 'see [Mappings](#mappings)', '')
            parts.append(f'| {r.parameter} | {r.type} | {r.default} | {r.meaning} | {r.differentiable} |')
        parts.append('')
    parts.append('### Mappings\n')
    for title, which in (('2D mapping parameters', 0), ('3D mapping parameters', 1)):
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


def update_readme(path: str, bench_results: str | None = None) -> None:
    """Rewrite README's generated sections: the plugin reference and (given the benchmark's
    ``results.md``) its summary lines."""
    import re
    text = open(path, encoding='utf-8').read()
    text = re.sub(r'<!-- BEGIN PLUGIN REFERENCE -->.*<!-- END PLUGIN REFERENCE -->',
                  lambda m: '<!-- BEGIN PLUGIN REFERENCE -->\n' + markdown()
                  + '<!-- END PLUGIN REFERENCE -->', text, flags=re.S)
    if bench_results:
        summary = open(bench_results, encoding='utf-8').read().split('## Summary')[1].strip()
        text = re.sub(r'<!-- BEGIN BENCH SUMMARY -->.*<!-- END BENCH SUMMARY -->',
                      lambda m: '<!-- BEGIN BENCH SUMMARY -->\n' + summary
                      + '\n<!-- END BENCH SUMMARY -->', text, flags=re.S)
    with open(path, 'w', encoding='utf-8') as f:
        f.write(text)
