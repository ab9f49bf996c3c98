"""The user documentation (README.md and docs/) holds together: every relative link and image
resolves, with its #anchor, and no page carries work-log labels or paths of one machine.

Pure file reading, the same on every rank: it runs serially and under mpirun alike."""

import glob
import os
import re

from conftest import ROOT

LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)\)")
FENCE = re.compile(r"^(```|~~~)")
WORKLOG = re.compile(r"[Ss]ession [0-9]+|[Ii]ssue [0-9]+")
MACHINE_PATHS = ("/work/", "/tmp/")

# Pages another branch replaces: docs/results/benchmarks.md takes over docs/benchmarks.md and
# docs/bench-*.md.  Until it lands, a link to it may dangle and the old pages are not checked;
# once the old pages are gone, the link must resolve and the new page is checked like any other.
REPLACED = {os.path.join("docs", "results", "benchmarks.md"): "docs/benchmarks.md"}
OLD_PAGES = re.compile(r"^docs/(benchmarks|bench-[\w-]+)\.md$")


def pages():
    found = [os.path.join(ROOT, "README.md")]
    found += sorted(glob.glob(os.path.join(ROOT, "docs", "**", "*.md"), recursive=True))
    return [p for p in found if not OLD_PAGES.match(os.path.relpath(p, ROOT))]


def prose_lines(path):
    """(line number, text) of the lines outside fenced code blocks."""
    inside = False
    with open(path) as fh:
        for number, line in enumerate(fh, 1):
            if FENCE.match(line.strip()):
                inside = not inside
                continue
            if not inside:
                yield number, line


def slug(heading):
    """The anchor GitHub gives a heading: lower case, punctuation dropped, spaces to hyphens."""
    text = re.sub(r"[^\w\- ]", "", heading.strip().lower())
    return text.replace(" ", "-")


def anchors(path):
    seen, out = {}, set()
    for _, line in prose_lines(path):
        m = re.match(r"^#{1,6} (.*)", line)
        if m:
            base = slug(m.group(1))
            n = seen.get(base, 0)
            out.add(base if n == 0 else f"{base}-{n}")
            seen[base] = n + 1
    return out


def pending(target):
    """A page another branch is about to add, while the page it replaces is still here."""
    rel = os.path.relpath(target, ROOT)
    old = REPLACED.get(rel)
    return old is not None and not os.path.exists(target) and os.path.exists(
        os.path.join(ROOT, old))


def test_every_relative_link_resolves():
    bad, checked = [], 0
    for page in pages():
        for number, line in prose_lines(page):
            for target in LINK.findall(line):
                if re.match(r"^[a-z]+:", target):  # http:, https:, mailto:
                    continue
                path, _, anchor = target.partition("#")
                dest = os.path.normpath(os.path.join(os.path.dirname(page), path)) if path \
                    else page
                where = f"{os.path.relpath(page, ROOT)}:{number}: {target}"
                checked += 1
                if pending(dest):
                    continue
                if not os.path.exists(dest):
                    bad.append(f"{where}: no such file")
                elif anchor and dest.endswith(".md") and anchor not in anchors(dest):
                    bad.append(f"{where}: no heading with the anchor #{anchor}")
    assert checked > 200
    assert not bad, "\n".join(bad)


def test_no_work_log_labels_or_machine_paths():
    bad = []
    for page in pages():
        with open(page) as fh:
            for number, line in enumerate(fh, 1):
                where = f"{os.path.relpath(page, ROOT)}:{number}"
                if WORKLOG.search(line):
                    bad.append(f"{where}: work-log label {WORKLOG.search(line).group(0)!r}")
                for p in MACHINE_PATHS:
                    if p in line:
                        bad.append(f"{where}: machine path {p!r}")
    assert not bad, "\n".join(bad)


def test_the_pages_of_the_map_exist():
    """docs/index.md links every page of docs/ but the images and data (and the pages being
    replaced), so that no page is orphaned."""
    index = os.path.join(ROOT, "docs", "index.md")
    linked = set()
    for _, line in prose_lines(index):
        for target in LINK.findall(line):
            linked.add(os.path.normpath(os.path.join(ROOT, "docs", target.partition("#")[0])))
    orphans = [os.path.relpath(p, ROOT) for p in pages()
               if p != index and os.path.relpath(p, ROOT) != "README.md" and p not in linked]
    assert not orphans, f"pages not in docs/index.md: {orphans}"
