"""The claims tables of a results page, generated from the result folders' own findings.

`docs/results/claims.json` names, per table, the committed result folders that are its columns;
each cell is that folder's verdict of the row's claim with its band, read from the folder's
`findings.md` (which `bulbjax report` writes from the folder's metrics, and
tests/test_results_regenerate.py keeps equal to them). `write_page` replaces every block
between `<!-- claims:NAME -->` and `<!-- /claims:NAME -->` of the page with its table, so the
page's verdicts and bands cannot drift from the numbers: `bulbjax report docs/results` rewrites
them, and tests/test_reproduce.py checks the page holds what this module generates.
"""

from __future__ import annotations

import json
import os
import re
from typing import Any

CLAIMS_FILE = "claims.json"
_ROW = re.compile(r"^\| (?P<claim>.+?) \| \*\*(?P<verdict>[^*]+)\*\* \| (?P<detail>.*) \|$")


def findings_rows(folder: str) -> dict[str, tuple[str, str]]:
    """{claim: (verdict, detail)} of a folder's findings.md, in its order."""
    with open(os.path.join(folder, "findings.md"), encoding="utf-8") as f:
        rows = [_ROW.match(line.strip()) for line in f]
    return {m["claim"]: (m["verdict"], m["detail"]) for m in rows if m}


def bands(detail: str) -> str:
    """The differences and bands of a verdict's numbers, each with the stream it follows where
    one is named ("π_rand +0.345 ± 0.033; π_curr +0.120 ± 0.050")."""
    out, stream = [], ""
    for m in re.finditer(r"(π_rand|π_curr)|= ([+-]\d+\.\d+) ± (\d+\.\d+|inf)", detail):
        if m.group(1):
            stream = m.group(1)
        else:
            out.append(f"{stream} {m.group(2)} ± {m.group(3)}".strip())
    return "; ".join(out)


def cell(verdict: str, detail: str, max_bands: int = 2) -> str:
    b = bands(detail)
    parts = b.split("; ")
    if len(parts) > max_bands:  # claims over many parts (every object, every other learner)
        b = f"{len(parts)} comparisons (findings.md)"
    return f"**{verdict}**" + (f", {b}" if b else "")


def table(results_dir: str, spec: dict[str, Any]) -> str:
    """One claims table: a row per claim (in the first column's order, then any other's), a
    column per folder of `spec["columns"]` (`{"label", "folder"}`), each cell a verdict with its
    band; "-" where a folder's findings have no such row."""
    cols = [(c["label"], findings_rows(os.path.join(results_dir, c["folder"]))) for c in spec["columns"]]
    claims = list(dict.fromkeys(k for _, rows in cols for k in rows))
    drop = spec.get("drop", [])  # rows whose claim, or every column's verdict, holds one of these
    claims = [c for c in claims if not any(d in c for d in drop)
              and not all(any(d in rows.get(c, ("-",))[0] for d in drop) for _, rows in cols)]
    head = f"| {spec.get('first', 'claim')} | " + " | ".join(label for label, _ in cols) + " |"
    lines = [head, "|" + "---|" * (len(cols) + 1)]
    for c in claims:
        cells = [cell(*rows[c]) if c in rows else "-" for _, rows in cols]
        lines.append(f"| {c} | " + " | ".join(cells) + " |")
    sources = ", ".join(f"[{c['folder']}](results/{c['folder']}/findings.md)" for c in spec["columns"])
    lines += ["", f"Generated from {sources} (`bulbjax report docs/results`)."]
    return "\n".join(lines)


def read_spec(results_dir: str) -> dict[str, Any]:
    path = os.path.join(results_dir, CLAIMS_FILE)
    if not os.path.exists(path):
        raise ValueError(f"{results_dir} has no {CLAIMS_FILE}: it names the folders of each claims table")
    with open(path, encoding="utf-8") as f:
        return json.load(f)


def render(page_text: str, results_dir: str) -> str:
    """`page_text` with every claims block regenerated (a block the spec does not name is an
    error, so a renamed table cannot silently keep old numbers)."""
    spec = read_spec(results_dir)

    def one(m: re.Match) -> str:
        name = m.group(1)
        if name not in spec["tables"]:
            raise ValueError(f"the page has a claims block {name!r} that {CLAIMS_FILE} does not define")
        return f"<!-- claims:{name} -->\n{table(results_dir, spec['tables'][name])}\n<!-- /claims:{name} -->"

    return re.sub(r"<!-- claims:([\w-]+) -->\n(?:.*?\n)?<!-- /claims:\1 -->", one, page_text, flags=re.S)


def write_page(results_dir: str) -> str:
    """Regenerate the claims blocks of the page `claims.json` names (default `../results.md`);
    returns its path."""
    spec = read_spec(results_dir)
    page = os.path.normpath(os.path.join(results_dir, spec.get("page", "../results.md")))
    with open(page, encoding="utf-8") as f:
        text = f.read()
    new = render(text, results_dir)
    with open(page, "w", encoding="utf-8") as f:
        f.write(new)
    return page
