"""scripts/bench's command line: ``NAME [options]``, ``list``, ``table RESULT.json``."""

import argparse
import importlib
import json
import os
import shlex
import shutil
import sys
import tempfile

from benchmarks import NAMES, harness

OUTPUTS = ("--json", "--doc", "--work")  # not part of the command that reproduces a run


def module(name):
    if name not in NAMES:
        raise SystemExit(f"bench: no benchmark {name!r} (one of {', '.join(NAMES)})")
    return importlib.import_module(f"benchmarks.{name}")


def reproducing(name, argv):
    """The command line of the page: this run's arguments without its output paths."""
    kept, skip = [], False
    for arg in argv:
        if skip:
            skip = False
        elif arg in OUTPUTS:
            skip = True
        elif not arg.startswith(tuple(o + "=" for o in OUTPUTS)):
            kept.append(harness.relpath(arg) if os.path.exists(arg) else arg)
    return " ".join(["scripts/bench", name] + [shlex.quote(a) for a in kept])


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    if not argv or argv[0] in ("-h", "--help", "list"):
        print(__doc__.split("\n")[0].replace("scripts/bench's", "scripts/bench:"))
        for name in NAMES:
            print(f"  {name:10s} {module(name).TITLE}")
        return 0
    if argv[0] == "table":  # the page's section again, from a saved result
        ap = argparse.ArgumentParser(prog="scripts/bench table")
        ap.add_argument("result")
        ap.add_argument("--doc", help="write the section into this page")
        args = ap.parse_args(argv[1:])
        with open(args.result) as fh:
            result = json.load(fh)
        text = harness.section(module(result["meta"]["benchmark"]), result)
        if args.doc:
            harness.write_doc(args.doc, result["meta"]["benchmark"], text)
        print(text)
        return 0
    name, mod = argv[0], module(argv[0])
    ap = argparse.ArgumentParser(prog=f"scripts/bench {name}", description=mod.__doc__)
    ap.add_argument("--quick", action="store_true", help="tiny sizes, a few seconds (CI)")
    ap.add_argument("--old", help="a commit to measure beside this tree (a git worktree of it)")
    ap.add_argument("--repo", default=harness.ROOT, help="the repository holding --old")
    ap.add_argument("--json", help=f"results (default bench-out/{name}.json)")
    ap.add_argument("--doc", help="write the table into this page, e.g. "
                    "docs/results/benchmarks.md")
    ap.add_argument("--work", help="scratch directory kept afterwards (default: a temporary one)")
    mod.add_arguments(ap)
    if "--quick" in argv[1:]:  # the quick sizes as defaults: options given still apply
        ap.set_defaults(**mod.QUICK)
    args = ap.parse_args(argv[1:])
    result = {"meta": harness.meta(name, reproducing(name, argv[1:]), args.old)}
    work = (os.path.abspath(args.work) if args.work
            else tempfile.mkdtemp(prefix=f"parjam-bench-{name}-"))
    os.makedirs(work, exist_ok=True)
    try:
        with harness.trees(args.old, args.repo) as trees:
            result["rows"] = mod.run(args, trees, work)
    finally:
        if not args.work:
            shutil.rmtree(work, ignore_errors=True)
    result["meta"]["load_end"] = os.getloadavg()[0]
    harness.save(args.json or os.path.join(harness.ROOT, "bench-out", f"{name}.json"), result)
    text = harness.section(mod, result)
    if args.doc:
        harness.write_doc(args.doc, name, text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
