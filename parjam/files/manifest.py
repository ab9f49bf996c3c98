"""The manifest of a ``parjam pack`` output directory: which members are finished, so that a killed
run restarted with the same command resumes without recomputing them (docs/explanation/reliability.md).

- ``DIR/manifest.json`` (written atomically by world rank 0 at the start and at the end of a run):
  the run's parameters (everything that determines the packings) and, per finished member, its
  files with their sha256;
- ``DIR/.manifest.d/memberNNNN.json`` (written atomically by the rank that wrote the member's
  files, right after them): the same record for one member, so that a member finished by any
  rank survives a kill before rank 0 rewrites the manifest.  Lock-free: each record has exactly
  one writer.

A member counts as finished only if its record exists and every file it lists exists with the
recorded sha256; anything else is recomputed (files are replaced atomically, never duplicated).
A directory whose manifest or files come from different parameters is refused.
"""

import glob
import json
import os
import re

import h5py

from parjam.files import inputs, outputs
from parjam.files.checkpoint import DIRECTORY
from parjam.errors import ParjamError
from parjam.files.h5md import sha256

FORMAT = "parjam-pack-manifest"
VERSION = 1
NAME = "manifest.json"
RECORDS = ".manifest.d"
# parameters of /parameters attrs in a packing file compared with this run's (file key, run key)
FILE_KEYS = (("dimension", "dim"), ("n", "n"), ("seed", "seed"), ("dispersity", "dispersity"),
             ("alpha", "alpha"), ("ftol", "ftol"))


def run_parameters(args):
    """Everything that determines the packings of a member (not --members, --out or -q)."""
    return {
        "dim": int(args.dim), "n": int(args.n), "dispersity": args.dispersity,
        "ratio": float(args.ratio), "alpha": float(args.alpha), "seed": int(args.seed),
        "dphi": sorted(float(x) for x in args.dphi) if args.dphi else None,
        "pressure": sorted(float(x) for x in args.pressure) if args.pressure else None,
        "phi": None if args.phi is None else float(args.phi),
        "ladder": args.ladder, "phi_start": float(args.phi_start), "ftol": float(args.ftol),
        "energy_window": [float(x) for x in args.energy_window],
        "no_phic_file": bool(args.no_phic_file),
        # only when not the default, so that directories written before the option resume
        **({"phic_method": args.phic_method}
           if getattr(args, "phic_method", "bisect") != "bisect" else {}),
        **({"start_sha256": args.start_sha256} if getattr(args, "start", None) else {}),
    }


def write_json(path, obj):
    """Atomic JSON write (parjam.files.outputs: temporary name, fsync, rename; a full disk is one
    line)."""
    outputs.write_bytes(path, json.dumps(obj, indent=1, sort_keys=True).encode())


def _read_json(path):
    try:
        with inputs.open_file(path, "r") as fh:  # a FIFO or a device here: refused, not read
            return json.load(fh)
    except (OSError, ValueError) as exc:
        raise ParjamError(f"{path}: unreadable manifest ({exc}); remove it to start afresh") \
            from None


def _bad(path, what):
    return ParjamError(f"{path}: not a valid parjam pack manifest ({what}); remove it to start "
                       f"afresh")


def _check_files(path, files):
    """{file name: sha256 hex} of one member, as written by write_member_record."""
    if not isinstance(files, dict) or not all(
            isinstance(k, str) and k and os.path.basename(k) == k and isinstance(v, str)
            for k, v in files.items()):
        raise _bad(path, "a member's files must map plain file names to sha256 strings")
    return files


def _check_record(path, rec):
    """A member record of the right structure (valid JSON of the wrong shape was a TypeError)."""
    if not isinstance(rec, dict):
        raise _bad(path, f"a JSON object expected, got {type(rec).__name__}")
    member = rec.get("member")
    if isinstance(member, bool) or not isinstance(member, int) or member < 0:
        raise _bad(path, f"member must be a non-negative integer, got {member!r}")
    if not isinstance(rec.get("parameters"), dict):
        raise _bad(path, "parameters must be a JSON object")
    _check_files(path, rec.get("files"))
    return rec


_MEMBER_FILE = re.compile(r"^member\d{4,}_.+\.h5$")


def owned(rel):
    """What parjam pack writes at a path relative to DIR: "file", "dir" or None (not pack's: a
    user's file beside them); parjam.files.outputs.tree_problems checks them before a run."""
    parts = rel.split(os.sep)
    if len(parts) == 1:
        if parts[0] == NAME or _MEMBER_FILE.match(parts[0]):
            return "file"
        return "dir" if parts[0] in (RECORDS, DIRECTORY) else None
    if parts[0] == RECORDS:
        return "file" if len(parts) == 2 else None
    if parts[0] == DIRECTORY:  # memberM.h5 and its pieces in memberM.d/
        return "dir" if len(parts) == 2 and parts[1].endswith(".d") else "file"
    return None


def record_path(out, member):
    return os.path.join(out, RECORDS, f"member{member:04d}.json")


def write_member_record(out, member, paths, params):
    """After a member's files are written: its record (file names and sha256)."""
    os.makedirs(os.path.join(out, RECORDS), exist_ok=True)
    rec = {"member": int(member), "parameters": params,
           "files": {os.path.basename(p): sha256(p) for p in paths}}
    write_json(record_path(out, member), rec)


def load(out):
    """The manifest dict of DIR, or None if there is none."""
    path = os.path.join(out, NAME)
    if not os.path.exists(path):
        return None
    man = _read_json(path)
    if not isinstance(man, dict) or man.get("format") != FORMAT:
        raise ParjamError(f"{path}: not a parjam pack manifest")
    if not isinstance(man.get("parameters"), dict):
        raise _bad(path, "parameters must be a JSON object")
    members = man.get("members", {})
    if not isinstance(members, dict):
        raise _bad(path, "members must be a JSON object")
    for key, files in members.items():
        if not key.isdigit():
            raise _bad(path, f"member key {key!r} is not a number")
        _check_files(path, files)
    return man


def _differences(a, b):
    keys = sorted(set(a) | set(b))
    return [f"{k}: {a.get(k)!r} there, {b.get(k)!r} now" for k in keys if a.get(k) != b.get(k)]


def check_parameters(out, params):
    """Refuse a directory holding results of other parameters (manifest, records or files)."""
    man = load(out)
    if man is not None and man.get("parameters") != params:
        diff = "; ".join(_differences(man.get("parameters") or {}, params))
        raise ParjamError(f"{out} holds packings made with other parameters ({diff}): use "
                          f"another --out")
    for path in sorted(glob.glob(os.path.join(out, RECORDS, "member*.json"))):
        rec = _check_record(path, _read_json(path))
        if rec.get("parameters") != params:
            diff = "; ".join(_differences(rec.get("parameters") or {}, params))
            raise ParjamError(f"{out} holds packings made with other parameters ({diff}): use "
                              f"another --out")
    for path in sorted(glob.glob(os.path.join(out, "member*.h5"))):
        _check_file(path, params, out)


def _check_file(path, params, out):
    why = inputs.problem(path)
    if why:  # a FIFO or a device named like a packing: never opened
        raise ParjamError(f"{why}; it is in the output directory {out}: remove it")
    try:
        with h5py.File(path, "r") as f:
            attrs = dict(f["parameters"].attrs) if "parameters" in f else {}
    except (OSError, KeyError):
        return  # an unreadable file is no result: it is recomputed (replaced) if it is ours
    for fkey, pkey in FILE_KEYS:
        if fkey not in attrs:
            continue
        have = attrs[fkey]
        have = have.decode() if isinstance(have, bytes) else have
        want = params[pkey]
        try:
            same = (have == want) if isinstance(want, str) else float(have) == float(want)
        except (TypeError, ValueError):  # an attribute of the wrong shape: not our file
            same = False
        if not same:
            raise ParjamError(f"{out} holds packings made with other parameters "
                              f"({os.path.basename(path)}: {fkey} = {have!r}, now {want!r}): "
                              f"use another --out")


def finished_members(out, params):
    """{member: {file: sha256}} of the members whose every file is present and intact, and the
    list of members whose record exists but whose files do not match it (recomputed)."""
    records = {}
    man = load(out)
    for key, files in ((man or {}).get("members") or {}).items():
        records[int(key)] = files
    for path in glob.glob(os.path.join(out, RECORDS, "member*.json")):
        rec = _check_record(path, _read_json(path))
        records[int(rec["member"])] = rec["files"]
    done, damaged = {}, []
    for m, files in sorted(records.items()):
        ok = all(os.path.isfile(os.path.join(out, name))
                 and sha256(os.path.join(out, name)) == digest for name, digest in files.items())
        if ok and files:
            done[m] = files
        else:
            damaged.append(m)
    return done, damaged


def write_manifest(out, params, done, stopped=None):
    """DIR/manifest.json with the parameters, the finished members and the members whose
    ladder stopped early (``stopped``: {member: dphi or pressure of the step that unjammed});
    a stopped member has no record, so the same command computes it again."""
    write_json(os.path.join(out, NAME), {
        "format": FORMAT, "version": VERSION, "parameters": params,
        "members": {str(m): files for m, files in sorted(done.items())},
        "stopped": {str(m): float(step) for m, step in sorted((stopped or {}).items())}})


_TMP = re.compile(r"^\..+\.tmp(\d+)$")


def temporary_dirs(out):
    """Where parjam pack writes through temporary files: DIR, its records and checkpoints."""
    return (out, os.path.join(out, RECORDS), os.path.join(out, DIRECTORY))


def remove_stale_temporaries(out):
    """Temporary files (.NAME.tmpPID) left by a killed process that no longer runs."""
    removed = []
    for directory in temporary_dirs(out):
        if not os.path.isdir(directory):
            continue
        for name in os.listdir(directory):
            m = _TMP.match(name)
            if m and not _pid_alive(int(m.group(1))):
                os.remove(os.path.join(directory, name))
                removed.append(name)
    return removed


def _pid_alive(pid):
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True
