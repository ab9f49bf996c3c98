"""``parjam run scene.toml``: a whole study from a scene file, stage by stage (parjam.study).

Layout of ``--out`` (default ``results/<scene name>``):

    stages/<stage name>/member0000_<state>.h5   packings (pack stages, the ``parjam pack`` files)
    stages/<stage name>/member0000.h5           one file per member of every analysis stage
    summary-<system>-<key>.h5                    ensemble means, errors and D(omega) averages
    stage.log                                    one line per member computed (never per skip)
    figures/*.png                                with [observables.pictures]

A stage's name ends with the hash of its inputs (system, protocol, seed, solver choices and the
keys of the stages it reads), so a changed scene recomputes exactly the stages whose inputs
changed.  A member's file is written atomically when the member is finished: re-running skips
finished members and stages, and an interrupted stage resumes at the first unfinished member.
Members are spread over groups of ranks (member m to group m % groups); with fewer members than
ranks a group shares a member (distributed minimisation, distributed matrices).
"""

import os

from parjam import env, resources
from parjam.files import outputs
from parjam.progress import Progress, Relay


def add_parser(sub):
    p = sub.add_parser(
        "run", help="run a scene: packings, spectra and observables described in a TOML file",
        description="Plan the stages a scene's observables need (parjam.study), then compute "
        "them member by member, storing each result in HDF5 as it finishes; re-running skips "
        "what is done and resumes an interrupted stage. --dry-run prints the plan.")
    p.add_argument("scene", help="scene file (TOML)")
    p.add_argument("--dry-run", action="store_true",
                   help="print the plan (stages, sizes, solver per stage, estimates) and stop")
    p.add_argument("--out", help="output directory (default results/<scene name>)")
    p.add_argument("--force", action="store_true",
                   help="run even if the memory/time estimate does not fit this machine")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress output")
    p.set_defaults(run=run, reads=lambda a: [a.scene])


def draw(pictures):
    """The scene's D(omega) figures (rank 0), from its summary files."""
    if not pictures:
        return
    from parjam.plot.spectra import dos_pictures

    os.makedirs(os.path.dirname(pictures[0][1]), exist_ok=True)
    for path, stem, dpi in pictures:
        dos_pictures(path, stem, dpi)


def run(args):
    # the study's modules load here, not when the command line is built (parjam --help)
    from parjam.study import plan, scene as scene_mod
    from parjam.study.runner import Runner, owned as runner_owned

    scene = scene_mod.load(args.scene)
    stages = plan.plan(scene)
    world = env.petsc().COMM_WORLD
    need = plan.machine_need(scene, stages, world.getSize(),
                             resources.ranks_on_node(world.tompi4py()))
    out = args.out or os.path.join("results", scene.name)
    if args.dry_run:
        text = resources.describe(*need)
        if world.getRank() == 0:
            print(plan.describe(scene, stages) + f"\nresults in {out}\n" + text, flush=True)
        return 0
    # the directory, and what a run writes in it: no symlink, FIFO or device at a stage's,
    # summary's or log's name, none of them the scene file (by identity)
    outputs.check(world, dirs=[("--out", out)], inputs=[args.scene],
                  trees=[("--out", out, runner_owned)])
    resources.check(world, need[0], need[1], args.force, f"scene {scene.name!r}")
    relay = Relay(world.tompi4py())  # every rank group's member lines reach world rank 0
    progress = Progress(world.tompi4py(), args.quiet, "run: ", relay=relay)
    runner = Runner(scene, stages, out, world, progress)
    code = runner.run()
    relay.close()
    if code == 0 and world.getRank() == 0:
        draw(runner.pictures())
    if world.getRank() == 0 and code == 0:
        print(runner.report(), flush=True)
    return code
