"""The runner of a scene: its stages member by member over groups of ranks (parjam.ranks), each
member's result stored atomically as it finishes; re-running skips what is done.

Layout of the output directory:

    stages/<stage name>/member0000_<state>.h5   packings (pack stages, the ``parjam pack`` files)
    stages/<stage name>/member0000.h5           one file per member of every analysis stage
    summary-<system>-<key>.h5                    ensemble tables (parjam.study.summary)
    stage.log                                    one line per member computed (never per skip)
    figures/*.png                                with [observables.pictures]
"""

import collections
import os
import sys
import time

from parjam import env
from parjam.files import h5md, inputs, manifest, outputs, rowio, stagefile
from parjam.study import members
from parjam.errors import ParjamError, UnjammedError
from parjam.net.fluctuations import contact_fluctuations
from parjam.progress import member
from parjam.ranks import member_groups
from parjam.study.records import moduli_record, network_record, softmodes_record, spectrum_record
from parjam.study.summary import summary_table, write_summary

EXIT_INTERRUPTED = 5


# --------------------------------------------------------------------------- member files

def owned(rel):
    """What a run writes at a path relative to its output directory ("file", "dir" or None:
    not the run's); parjam.files.outputs.tree_problems checks them before a run."""
    parts = rel.split(os.sep)
    if len(parts) == 1:
        if parts[0] in ("stages", "figures"):
            return "dir"
        return "file" if parts[0] == "stage.log" or parts[0].startswith("summary-") else None
    if parts[0] == "figures":
        return "file" if len(parts) == 2 else None
    if parts[0] == "stages":  # a stage's directory: its member files, a pack stage's manifest
        return "dir" if len(parts) == 2 else (manifest.owned(os.path.join(*parts[2:])) or "file")
    return None


# --------------------------------------------------------------------------- the runner

class Runner:
    """A scene's stages (parjam.study.plan) run into ``out``.  ``counts`` tells what this
    process computed: members per stage kind and summaries written (nothing on a re-run)."""

    def __init__(self, scene, stages, out, world, progress, stop_after=None):
        self.scene, self.stages, self.out = scene, stages, out
        self.world, self.mpi = world, world.tompi4py()
        self.progress = progress
        #: stop (as if interrupted) after this many members computed in this process
        self.stop_after = stop_after
        self.computed = 0
        self.summaries = {}
        self.pack_dirs = {}
        self.counts = collections.Counter()

    # paths -------------------------------------------------------------------
    def stage_dir(self, st):  # names are one path component (parjam.study.scene): inside out
        return inputs.inside(self.out, "stages", st.name)

    def part_path(self, st, m):
        return os.path.join(self.stage_dir(st), f"member{m:04d}.h5")

    def pack_path(self, system, m, label):
        return os.path.join(self.pack_dirs[system.name], f"member{m:04d}_{label}.h5")

    def summary_path(self, st):
        return inputs.inside(self.out, f"summary-{st.system.name}-{st.key}.h5")

    def failed_path(self, system, m):
        return os.path.join(self.pack_dirs[system.name], f"member{m:04d}.failed")

    def failed(self, system, m):
        """The member's packing could not be made (it did not jam): left out of everything."""
        return os.path.isfile(self.failed_path(system, m))

    def member_done(self, st, m):
        if self.failed(st.system, m):
            return True
        if st.kind == "pack":
            d = self.stage_dir(st)
            return all(os.path.isfile(os.path.join(d, f"member{m:04d}_{lab}.h5"))
                       for lab in st.states)
        return os.path.isfile(self.part_path(st, m))

    def log(self, st, m):
        self.append_log(f"computed {st.name} {member(m)}")

    def append_log(self, text):
        """One timestamped line appended to OUT/stage.log (a failed write is one line)."""
        path = os.path.join(self.out, "stage.log")
        try:
            with open(path, "a") as fh:
                fh.write(f"{time.strftime('%Y-%m-%dT%H:%M:%S')} {text}\n")
        except OSError as exc:
            raise ParjamError(f"{path}: cannot write ({exc.strerror or exc})",
                              collective=False) from None

    # the loop ----------------------------------------------------------------
    def run(self):
        PETSc = env.petsc()
        if self.mpi.Get_rank() == 0:
            os.makedirs(self.out, exist_ok=True)
        self.mpi.Barrier()
        comm, mine = member_groups(self.world, self.scene.members)
        self.comm = comm
        stage = PETSc.Log.Stage("parjam run")
        stage.push()
        stopped = False
        try:
            for st in self.stages:
                if st.kind == "pack":
                    self.pack_dirs[st.system.name] = self.stage_dir(st)
                if st.kind == "summary":
                    # a member's stages all run in the same group, so groups only wait for each
                    # other here, where the summary reads every member
                    if self.mpi.allreduce(int(stopped)) > 0:
                        self.progress("interrupted: re-run the same command to resume")
                        return EXIT_INTERRUPTED
                    self.summarise(st)
                elif not stopped:
                    stopped = self.run_stage(st, comm, mine)
        finally:
            stage.pop()
        self.mpi.Barrier()
        return 0

    def run_stage(self, st, comm, mine):
        """This group's unfinished members of one stage; True if stopped early."""
        gm = comm.tompi4py()
        todo = gm.bcast([m for m in mine if not self.member_done(st, m)] if gm.Get_rank() == 0
                        else None, root=0)
        label = f"{st.kind}{' ' + st.matrix if st.matrix else ''} {st.system.name}"
        group_progress = self.progress.group(comm.tompi4py(), "")  # relayed to world rank 0
        if len(todo) < len(mine):
            group_progress(f"{label}: {len(mine) - len(todo)} member(s) of this rank's group "
                           f"already done")
        if gm.Get_rank() == 0:
            os.makedirs(self.stage_dir(st), exist_ok=True)
        gm.Barrier()
        for m in todo:
            if self.stop_after is not None and self.computed >= self.stop_after:
                return True
            t0 = time.time()
            self.compute_member(st, m, comm)
            self.computed += 1
            self.counts[st.kind] += 1
            if gm.Get_rank() == 0:
                self.log(st, m)
            group_progress(f"{label}: {member(m, self.scene.members)} in "
                           f"{time.time() - t0:.1f} s")
        return False

    def compute_member(self, st, m, comm):
        if st.kind == "pack":
            protocol = self.scene.packing_protocol(st.system, self.stage_dir(st))
            sub = self.progress.sub(f"pack {st.system.name} {member(m)}: ")
            sub.enabled = False  # the bisection's lines would drown the stage progress
            try:
                members.pack_member(protocol, m, comm, sub)
            except UnjammedError as exc:  # rare: the member is left out, the ensemble goes on
                if comm.getRank() == 0:
                    outputs.write_bytes(self.failed_path(st.system, m), f"{exc}\n".encode())
                    print(f"parjam: warning: {st.system.name} {member(m)}: {exc}; left out",
                          file=sys.stderr, flush=True)
            return
        data = {}
        for label in st.states:
            path = self.pack_path(st.system, m, label)
            try:
                data[label] = self.state_record(st, comm, path, label)
            except ParjamError as exc:
                # e.g. a ladder state left with fewer contacts than isostatic (floppy modes):
                # raised by this member's group only, so record it and go on (raising it would
                # leave the other groups waiting for this one)
                data[label] = {"failed": str(exc)}
                if comm.getRank() == 0:
                    print(f"parjam: warning: {st.kind} {st.system.name} {member(m)} {label}: "
                          f"{exc}; recorded as missing", file=sys.stderr, flush=True)
        if comm.getRank() == 0:
            stagefile.write_part(self.part_path(st, m), data,
                       {"stage": st.name, "member": m, "kind": st.kind})

    def state_record(self, st, comm, path, label):
        """One state's record; every kind but the contact fluctuations (a serial count over
        sub-boxes) reads only this rank's rows of the file."""
        if st.kind == "fluctuations":
            return contact_fluctuations(h5md.read_packing(path), st.params["max_divisions"])
        rows = rowio.read_rows(comm, path)
        if st.kind == "network":
            return network_record(comm, rows)
        if st.kind == "spectrum":
            return spectrum_record(comm, rows, st.matrix, st.params[label],
                                   self.scene.solver["tol"])
        if st.kind == "moduli":
            return moduli_record(comm, rows)
        if st.kind == "softmodes":
            return softmodes_record(comm, rows, st.params)
        raise ValueError(f"unknown stage kind {st.kind}")

    # the summary -------------------------------------------------------------
    def summarise(self, st):
        """Ensemble tables of one system (world rank 0), skipped when already written."""
        path = self.summary_path(st)
        self.summaries[st.system.name] = path
        if self.mpi.Get_rank() == 0 and not os.path.isfile(path):
            self.counts["summary"] += 1
            by_kind = {}
            for dep in self.stages:
                if dep.key in st.deps and dep.kind != "pack":
                    tag = dep.kind + (f"/{dep.matrix}" if dep.matrix else "")
                    by_kind[tag] = [stagefile.read_part(self.part_path(dep, m))
                                    for m in range(self.scene.members)
                                    if not self.failed(st.system, m)]
            failed = [m for m in range(self.scene.members) if self.failed(st.system, m)]
            write_summary(path, st, by_kind, self.scene, failed)
            self.append_log(f"computed {st.name}")
        self.mpi.Barrier()

    def report(self):
        lines = [f"scene {self.scene.name}: results in {self.out}"]
        for name, path in self.summaries.items():
            lines.append(summary_table(path))
        return "\n".join(lines)

    def pictures(self):
        """(summary file, figure stem, dpi) of each system's D(omega) figures, when the scene
        asks for [observables.pictures] (drawn by ``parjam run``, parjam.plot.spectra)."""
        if "pictures" not in self.scene.observables:
            return []
        fig_dir = os.path.join(self.out, "figures")
        dpi = self.scene.observables["pictures"]["dpi"]
        return [(path, os.path.join(fig_dir, name), dpi) for name, path in self.summaries.items()]
