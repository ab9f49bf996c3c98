"""docs/reference/commands.md is generated from the argument parser (scripts/docs_reference.py)
and must not drift from it: a changed option, default or help text fails here until the page is
regenerated.  The comparison is in memory on every rank (no file is written), so it runs
serially and under mpirun alike."""

import importlib.util
import os
import re

from conftest import ROOT

PAGE = os.path.join(ROOT, "docs", "reference", "commands.md")


def generator():
    path = os.path.join(ROOT, "scripts", "docs_reference.py")
    spec = importlib.util.spec_from_file_location("docs_reference", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_commands_page_is_the_parsers_help():
    with open(PAGE) as fh:
        committed = fh.read()
    generated = generator().render()
    if committed != generated:
        diff = [f"line {k + 1}: page {a!r} != parser {b!r}"
                for k, (a, b) in enumerate(zip(committed.splitlines(), generated.splitlines()))
                if a != b][:3]
        raise AssertionError("docs/reference/commands.md is stale: run "
                             ".venv/bin/python scripts/docs_reference.py\n" + "\n".join(diff))


def test_commands_page_covers_every_command_and_option():
    gen = generator()
    text = gen.render()
    names = gen.command_names()
    assert len(names) >= 12 and {"pack", "modes", "run", "softmodes"} <= set(names)
    for name in names:
        assert f"\n## parjam {name}\n" in text, name
        assert f"usage: parjam {name} " in text, name
    # a few options with their defaults, as a user reads them
    for fragment in ("--checkpoint-every SECONDS", "--dphi DPHI [DPHI ...]", "(default: 64)",
                     "--moments MOMENTS     kpm: Chebyshev moments (256)"):
        assert fragment in text, fragment
    assert "(default: )" not in text  # an empty list default is not shown as an empty value


def test_page_does_not_depend_on_the_terminal(monkeypatch):
    gen = generator()
    monkeypatch.setenv("COLUMNS", "37")
    narrow = gen.render()
    monkeypatch.setenv("COLUMNS", "250")
    wide = gen.render()
    assert narrow == wide
    assert os.environ["COLUMNS"] == "250"  # the caller's environment is restored
    blocks = re.findall(r"```text\n(.*?)```", wide, flags=re.S)
    longest = max(len(line) for text in blocks for line in text.splitlines())
    assert longest <= gen.WIDTH
