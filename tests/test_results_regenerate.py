"""Every committed result regenerates (issue 57): `bulbjax report`'s own code, run on each
committed result folder (a merged one on the halves beside it, `merge.merge_sources`) from its
committed metrics, writes the committed `table.md` and `findings.md` again, the footer line of
`table.md` aside (it says how and when the file was written: a run's wall time, "redrawn by
`bulbjax report` from N records", or the merged runs' paths on the machine that merged them).

Folders of `docs/results/` and `benchmarks/results/` with a `table.md` are all covered: those
whose metrics are in the tree are redrawn (PNGs not drawn: `figures=False` writes the same
Markdown through the same code, in ~0.1-1 s a folder); those whose metrics left the tree are
listed with the commit that holds them (`BULBJAX_CHECK_HISTORY=1` brings them back with git and
checks them too); the few that never had their metrics committed are listed with why. A new
folder must be one of the three. CPU only.
"""

from __future__ import annotations

import glob
import os
import shutil
import subprocess

import pytest

from bulbjax.report import merge, report

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
RESULT_ROOTS = ("docs/results", "benchmarks/results")
# folder -> the commit whose tree still has its metrics (a merged folder: its halves' folders)
IN_HISTORY = {
    "docs/results/ant_h100": "ac65cf8~1",
    "docs/results/fig2_invpend_3xh100_1000": "e01e52c",
    "docs/results/fig2_invpend_h100_1000/seed0": "45add11",
    "docs/results/fig2_invpend_h100_1000/seed1": "45add11",
    "docs/results/fig2_invpend_h100_1000/merged": "45add11",
    "docs/results/fig2_invpend_h100_6seeds/seed0": "2d445d2",
    "docs/results/fig2_invpend_h100_6seeds/seed1": "2d445d2",
    "docs/results/fig2_invpend_h100_6seeds/merged": "2d445d2",
    "docs/results/fig2_invpend_variants_2xh200": "23306e6",
    "benchmarks/results/multigpu_run_fig2-invpend_2xh200_20261125": "8962cf7~1",
}
# folders whose metrics were never committed: their table.md is the run's record of itself
NEVER_COMMITTED = {
    "benchmarks/results/multigpu_run_fig2-invpend_2xh200_20261126": "a two-GPU benchmark run; its "
    "metrics stayed on the machine (config, logs and tables kept)",
    "benchmarks/results/multigpu_run_fig3-rearrange-geom_2xh200_20261126": "a two-GPU benchmark run; "
    "its metrics stayed on the machine (config, logs and table kept)",
}


def report_folders() -> list[str]:
    """Every folder under RESULT_ROOTS with a table.md, relative to the repository."""
    found = set()
    for top in RESULT_ROOTS:
        for path in glob.glob(os.path.join(ROOT, top, "**", "table.md"), recursive=True):
            found.add(os.path.relpath(os.path.dirname(path), ROOT))
    return sorted(found)


def _has_metrics(folder: str) -> bool:
    names = ("metrics.jsonl", "metrics.jsonl.gz", "curves.jsonl", "curves.jsonl.gz")
    return any(os.path.exists(os.path.join(folder, n)) for n in names)


def _readable(folder: str) -> bool:
    """A run's records are in the tree: its metrics, or a merged folder's runs' (`merge.run_records`
    pools them again: a plan folder of `bulbjax reproduce` keeps no second copy)."""
    if _has_metrics(folder):
        return True
    return _merged(folder) and all(_has_metrics(h) for h in merge.merge_sources(folder))


def _merged(folder: str) -> bool:
    return merge.is_merged(folder)


def protocol_tables() -> list[str]:
    """Folders of `bulbjax report --probe-protocol` tables: drawn from the runs they name."""
    return [d for d in report_folders() if _protocol_sources(d) is not None]


def _protocol_sources(folder: str) -> tuple[list[str], list[str]] | None:
    """The runs and fp32 runs a probe-protocol table names (`run `X``, `fp32 run `Y``), or None
    for any other report folder."""
    import re

    with open(os.path.join(ROOT, folder, "table.md")) as f:
        text = f.read()
    if not text.startswith("# Probe protocol"):
        return None
    return re.findall(r"^run `([^`]+)`", text, re.M), re.findall(r"fp32 run `([^`]+)`", text)


def in_tree() -> list[str]:
    return [d for d in report_folders()
            if d not in IN_HISTORY and d not in NEVER_COMMITTED and d not in protocol_tables()]


def regenerate(folder: str, out: str) -> str:
    """The folder's reports written again into `out` (a fresh folder) from its inputs: a merged
    folder from its halves, any other from a copy of its files but the reports and PNGs."""
    if _merged(folder):
        merge.merge_seeds(merge.merge_sources(folder), out, figures=False)
    else:
        shutil.copytree(folder, out, ignore=shutil.ignore_patterns("*.png", "table.md", "findings.md"))
        report.redraw(out, figures=False)
    return out


def differences(committed: str, regenerated: str, footer: bool) -> list[str]:
    """Lines that differ between a committed report and the regenerated one (`footer`: the
    regenerated file ends with a footer line, after an empty one; the committed one may end with
    its own or none)."""
    new = regenerated.rstrip("\n").split("\n")
    old = committed.rstrip("\n").split("\n")
    if footer:
        assert new[-2] == "", "a regenerated table.md ends with an empty line and its footer"
        new = new[:-2]
        if old[:-2] == new and old[-2] == "":
            return []
    if old == new:
        return []
    import difflib

    return list(difflib.unified_diff(old, new, "committed", "regenerated", lineterm="", n=0))[:30]


def check(folder: str, out: str) -> None:
    regenerate(folder, out)
    compared = 0
    for name, footer in (("table.md", True), ("findings.md", False)):
        path = os.path.join(folder, name)
        if not os.path.exists(path):
            continue
        with open(path) as f, open(os.path.join(out, name)) as g:
            diff = differences(f.read(), g.read(), footer)
        assert not diff, f"{folder}/{name} does not regenerate:\n" + "\n".join(diff)
        compared += 1
    assert compared, f"{folder} has no table.md or findings.md"


def test_every_report_folder_is_covered():
    """Each folder with a table.md is regenerated, listed with the commit holding its metrics,
    or listed as never having had them; the lists stay true."""
    folders = report_folders()
    assert len(folders) > 30 and "docs/results/fig2_invpend_h100_6seeds/merged" in folders
    for d in folders:
        full = os.path.join(ROOT, d)
        if d in IN_HISTORY or d in NEVER_COMMITTED:
            assert not _has_metrics(full), f"{d} has its metrics again: remove it from the lists"
        elif _protocol_sources(d) is not None:
            runs, fp32 = _protocol_sources(d)
            assert runs and all(_readable(os.path.join(ROOT, r)) for r in runs + fp32), d
        elif _merged(full):
            assert all(_has_metrics(h) for h in merge.merge_sources(full)), d
        else:
            assert _has_metrics(full), (f"{d} has a table.md but no metrics: commit them, or list it in "
                                        "IN_HISTORY (with the commit that has them) or NEVER_COMMITTED")
    assert set(IN_HISTORY) | set(NEVER_COMMITTED) <= set(folders)


@pytest.mark.parametrize("folder", in_tree())
def test_committed_reports_regenerate(folder, tmp_path, monkeypatch):
    monkeypatch.chdir(ROOT)  # merged folders name their halves relative to the repository
    check(folder, str(tmp_path / "out"))


@pytest.mark.parametrize("folder", protocol_tables())
def test_probe_protocol_tables_regenerate(folder, monkeypatch):
    """A committed `bulbjax report --probe-protocol` table, drawn again from the runs it names
    (issue 59: docs/results/probe_protocol), is the committed file."""
    from bulbjax.report.protocol import probe_protocol_table

    monkeypatch.chdir(ROOT)
    runs, fp32 = _protocol_sources(folder)
    with open(os.path.join(folder, "table.md")) as f:
        committed = f.read()
    diff = differences(committed, probe_protocol_table(runs, fp32), footer=False)
    assert not diff, f"{folder}/table.md does not regenerate:\n" + "\n".join(diff)


@pytest.mark.skipif(os.environ.get("BULBJAX_CHECK_HISTORY") != "1",
                    reason="set BULBJAX_CHECK_HISTORY=1 to bring the metrics back from git history")
@pytest.mark.parametrize("folder", sorted(IN_HISTORY))
def test_reports_of_metrics_in_history_regenerate(folder, tmp_path, monkeypatch):
    """The folders whose metrics left the tree, with those metrics from git (a copy of the
    folder in tmp_path, laid out as in the repository)."""
    monkeypatch.chdir(tmp_path)
    copies = [folder]
    if _merged(os.path.join(ROOT, folder)):
        copies += [os.path.relpath(h, ROOT) for h in merge.merge_sources(os.path.join(ROOT, folder))]
    for d in copies:
        shutil.copytree(os.path.join(ROOT, d), d)
        if not _merged(d):
            blob = subprocess.run(["git", "-C", ROOT, "show", f"{IN_HISTORY[d]}:{d}/metrics.jsonl.gz"],
                                  check=True, capture_output=True).stdout
            with open(os.path.join(d, "metrics.jsonl.gz"), "wb") as f:
                f.write(blob)
    check(folder, str(tmp_path / "out"))


def test_a_changed_number_is_caught(tmp_path, monkeypatch):
    """The check of the check: a committed table with one number changed, or a findings file
    with a verdict changed, does not pass; a different footer line does."""
    monkeypatch.chdir(ROOT)
    folder = "docs/results/fig2_cartpole_h100_1000/seed1"
    out = regenerate(folder, str(tmp_path / "out"))
    with open(os.path.join(folder, "table.md")) as f:
        table = f.read()
    with open(os.path.join(out, "table.md")) as f:
        new = f.read()
    assert not differences(table, new, footer=True)
    assert not differences(table.rstrip("\n").rsplit("\n", 1)[0] + "\nanother footer\n", new, footer=True)
    first = next(line for line in table.split("\n") if line.startswith("| vae |"))
    changed = first.replace(first.split(" | ")[2], "9.999 ± 0.001", 1)
    assert differences(table.replace(first, changed), new, footer=True)
    with open(os.path.join(folder, "findings.md")) as f, open(os.path.join(out, "findings.md")) as g:
        findings, regenerated = f.read(), g.read()
    assert "**holds**" in findings and not differences(findings, regenerated, footer=False)
    assert differences(findings.replace("**holds**", "**undecided**", 1), regenerated, footer=False)


def test_the_campaign_page_regenerates(tmp_path):
    """docs/results/paper_h200/results.md (issue 64's campaign, `bulbjax report` of its plan
    folder) is what the page's own code writes from the runs and summaries committed beside it."""
    from bulbjax.reproduce import results

    folder = os.path.join(ROOT, "docs", "results", "paper_h200")
    out = str(tmp_path / "paper_h200")
    shutil.copytree(folder, out, ignore=shutil.ignore_patterns("results.md"))
    results.write(out, results.read_summary(out), out_name="docs/results/paper_h200")
    with open(os.path.join(folder, "results.md")) as f, open(os.path.join(out, "results.md")) as g:
        assert f.read() == g.read()
