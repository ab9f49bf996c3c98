"""The file of one member of an analysis stage of ``parjam run`` (parjam.study.runner):
/<state>/<name> datasets (and string attributes) of the records of parjam.study.records,
written atomically."""

import h5py
import numpy as np

from parjam.files import h5md


def write_part(path, data, attrs=None):
    """{state: {name: array or scalar}} -> /<state>/<name>, atomically."""
    with h5md.atomic_h5(path) as f:
        for key, val in (attrs or {}).items():
            f.attrs[key] = val
        for state, values in data.items():
            g = f.create_group(state)
            for name, val in values.items():
                if isinstance(val, str):
                    g.attrs[name] = val
                else:
                    g.create_dataset(name, data=np.asarray(val))


def read_part(path):
    """A member's file of an analysis stage as {state: {name: value}} (write_part's inverse)."""
    with h5py.File(path, "r") as f:
        return {state: {**{k: v[()] for k, v in f[state].items()}, **dict(f[state].attrs)}
                for state in f}
